import os

# Tests use at most the machine's 2 cores and no network (wandb offline).
os.environ.setdefault("WANDB_MODE", "offline")
os.environ.setdefault("OMP_NUM_THREADS", "2")
