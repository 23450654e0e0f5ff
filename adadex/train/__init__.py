"""The training layer, the top of sim < data < envs < modules < transforms < eval < train: the loops
that fit the modules (today the point-cloud encoder's training, evaluation and command)."""
