from .navigation import NavigationEnv, check_env_config

__all__ = ["NavigationEnv", "check_env_config"]
