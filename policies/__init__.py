"""Navigation policies: localizability maps, planner, RL training (imports l3e_env only)."""
