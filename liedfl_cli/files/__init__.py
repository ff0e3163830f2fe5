"""liedfl's own files and the process safety around them: atomic writes and cluster-safe temporary
names, checkpoints, rollout files, run-folder locks, SIGTERM/SIGINT as exceptions with a phase, the
SHA-256 identity of a run's dataset file."""
