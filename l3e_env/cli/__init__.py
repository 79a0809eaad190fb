"""The `l3e` command line: parse, call the library, print."""

from l3e_env.core.threads import settle_process_threads

settle_process_threads()  # before numpy and torch load: the command owns its process
