from .evaluation import run_extra_evals  # noqa: F401  (moved to liedfl_cli.evaluation; kept until train.py imports it there)
