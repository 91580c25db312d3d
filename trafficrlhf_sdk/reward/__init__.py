"""Reward models (stage II of TrafficRLHF): r_HF, learned from preferences, shared as safetensors.

- :class:`RewardModel`: the base class; :class:`CTGMLPRewardModel` (``"ctg_mlp"``) the paper's architecture;
  :class:`RewardEnsemble` a bootstrap ensemble. ``RewardModel.from_pretrained(dir)`` loads any registered
  architecture from ``config.json`` + ``model.safetensors``; :class:`TrafficGenMCGRewardModel`
  (``"trafficgen_mcg"``) the same head on a TrafficGen-style (multi-context gating) encoder.
- :class:`RewardConfig` + :class:`RewardTrainer`: Bradley–Terry training from a
  :class:`~trafficrlhf_sdk.feedback.PreferenceDataset`.
- :func:`train_and_save`: training, the held-out test and the saved folder with its card (:func:`model_card`);
  :func:`describe_reward_model` reads a saved one back.
"""

from trafficrlhf_sdk.reward.card import TrainedRewardModel, describe_reward_model, model_card, train_and_save
from trafficrlhf_sdk.reward.config import RewardConfig
from trafficrlhf_sdk.reward.ctg_mlp import CTGMLPConfig, CTGMLPRewardModel
from trafficrlhf_sdk.reward.data import PairData, build_pair_data, filter_pairs, split_by_context
from trafficrlhf_sdk.reward.losses import bradley_terry_loss, preference_metrics
from trafficrlhf_sdk.reward.model import (
    RewardEnsemble,
    RewardModel,
    get_reward_model_architecture,
    reward_model_architectures,
)
from trafficrlhf_sdk.reward.trafficgen_mcg import TrafficGenMCGConfig, TrafficGenMCGRewardModel
from trafficrlhf_sdk.reward.trainer import RewardTrainer, TrainingResult, evaluate_pairs

__all__ = [
    "CTGMLPConfig",
    "CTGMLPRewardModel",
    "PairData",
    "RewardConfig",
    "RewardEnsemble",
    "RewardModel",
    "RewardTrainer",
    "TrafficGenMCGConfig",
    "TrafficGenMCGRewardModel",
    "TrainedRewardModel",
    "TrainingResult",
    "bradley_terry_loss",
    "build_pair_data",
    "describe_reward_model",
    "evaluate_pairs",
    "filter_pairs",
    "get_reward_model_architecture",
    "model_card",
    "preference_metrics",
    "reward_model_architectures",
    "split_by_context",
    "train_and_save",
]
