"""Policy components as TensorDictModules: the point-cloud encoder (object latent), the tracker
(specialist / generalist actor + critic) and the modulator (R/O/T heads)."""
