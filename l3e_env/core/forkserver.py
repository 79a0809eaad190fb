"""Imported first by the fork server that the project's worker processes come from
(`workers.process_context`), and by nothing else: the server dies with the process that started it.
Its workers die with the server (`workers.worker_start`), so a killed run leaves none behind; without
this the workers, which hold the server's keep-alive pipe, and the server would wait on each other."""

from l3e_env.core.workers import die_with_parent

die_with_parent()
