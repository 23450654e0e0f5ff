"""The training layer: PPO trackers on TorchRL collectors (specialists, the vanilla-PPO baseline),
point-cloud encoder training, and what they share (configs, env factories, checkpoints, logs).

The top of the library's stack: it may import every other layer; nothing below imports it.

The names below are re-exported here (``from adadex.train import PPOTrainer, TrainConfig``) and
imported on first use.
"""

from typing import TYPE_CHECKING

from adadex._exports import lazy_exports

_EXPORTS = {
    "adadex.train.ppo": ("PPOTrainer", "train", "default_loss", "TrainingDiverged"),
    "adadex.train.config": ("TrainConfig", "PPOConfig", "PolicyConfig", "CollectorConfig",
                            "ModulatorSettings", "SimConfig"),
    "adadex.train.envs": ("TrackingEnvFactory", "ModulatedEnv", "StatePrimer"),
    "adadex.train.collectors": ("make_collector", "local_collector"),
    "adadex.train.distill": ("Distiller", "DistillConfig", "distill"),
    "adadex.train.encoder": ("train_encoder", "evaluate_encoder"),
    "adadex.train.checkpoint": ("save_checkpoint", "load_checkpoint"),
    "adadex.train.logs": ("RunLog", "read_metrics"),
    "adadex.train.rollouts": ("teacher_rollouts", "load_rollouts"),
    "adadex.train.paired_choice": ("fit_paired_choice", "PairedChoiceConfig"),
    "adadex.train.pipeline": ("PipelineConfig", "run_pipeline", "SpecialistStage", "RolloutStage", "DistillStage",
                              "ModulatorStage", "BaselineStage", "EvaluationStage"),
    "adadex.train.table_so_far": ("table_so_far",),
}
__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:      # the same names, for type checkers and IDEs
    from adadex.train.ppo import PPOTrainer, train, default_loss, TrainingDiverged
    from adadex.train.config import TrainConfig, PPOConfig, PolicyConfig, CollectorConfig, ModulatorSettings, SimConfig
    from adadex.train.envs import TrackingEnvFactory, ModulatedEnv, StatePrimer
    from adadex.train.collectors import make_collector, local_collector
    from adadex.train.distill import Distiller, DistillConfig, distill
    from adadex.train.encoder import train_encoder, evaluate_encoder
    from adadex.train.checkpoint import save_checkpoint, load_checkpoint
    from adadex.train.logs import RunLog, read_metrics
    from adadex.train.rollouts import teacher_rollouts, load_rollouts
    from adadex.train.paired_choice import fit_paired_choice, PairedChoiceConfig
    from adadex.train.pipeline import (PipelineConfig, run_pipeline, SpecialistStage, RolloutStage, DistillStage,
                                       ModulatorStage, BaselineStage, EvaluationStage)
    from adadex.train.table_so_far import table_so_far
