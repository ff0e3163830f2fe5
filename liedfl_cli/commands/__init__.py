"""The work behind each CLI command: train (with its validation, fine-tuning and loggers' feed),
rollout, eval, report, and the job status of runs and sweeps."""
