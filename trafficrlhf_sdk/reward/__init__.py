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

from trafficrlhf_sdk.lazy import lazy_exports

# torch loads with the first name that needs it: reading and checking a RewardConfig does not
_EXPORTS = {
    "TrainedRewardModel": "card",
    "describe_reward_model": "card",
    "model_card": "card",
    "train_and_save": "card",
    "RewardConfig": "config",
    "CTGMLPConfig": "ctg_mlp",
    "CTGMLPRewardModel": "ctg_mlp",
    "PairData": "data",
    "build_pair_data": "data",
    "filter_pairs": "data",
    "split_by_context": "data",
    "bradley_terry_loss": "losses",
    "preference_metrics": "losses",
    "RewardEnsemble": "model",
    "RewardModel": "model",
    "get_reward_model_architecture": "model",
    "reward_model_architectures": "model",
    "TrafficGenMCGConfig": "trafficgen_mcg",
    "TrafficGenMCGRewardModel": "trafficgen_mcg",
    "RewardTrainer": "trainer",
    "TrainingResult": "trainer",
    "evaluate_pairs": "trainer",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
