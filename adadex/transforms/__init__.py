"""TorchRL transforms for the three modulation channels — reference (R), object latent (O),
action (T) — and the tracker-in-the-loop transform that turns a TrackingEnv into the modulator's env."""
