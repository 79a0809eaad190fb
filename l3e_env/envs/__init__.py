from .navigation import NavigationEnv

__all__ = ["NavigationEnv"]
