"""Navigation policies: localizability maps, planner, RL training (imports l3e_env only)."""

# metres between a map's positions by default, 4 headings each (`--resolution` of l3e policy map, plan and
# evaluate); here, where the command line reads it without loading the maps' libraries
MAP_RESOLUTION = 2.0
