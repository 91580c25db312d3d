"""The RLHF pipeline as idempotent steps, under every front-end (``trafficrlhf rlhf``, ``experiment paper``, your
own scripts).

generate candidates into a campaign -> label them -> train a reward model and its card -> align -> evaluate over
seeds: each stage is one step function (:mod:`~trafficrlhf_sdk.pipeline.stages`) that writes an output folder and
a manifest, ``step.json`` (:mod:`~trafficrlhf_sdk.pipeline.step`). Calling a step again with the same inputs
returns its recorded outputs without doing any work; a step stopped midway (no manifest) runs again; a finished
step asked for with other inputs is refused, naming what differs, unless it is overwritten. That is the one cache
and the one way to resume: a front-end re-runs its steps in order and the finished ones return at once.

Example: one rung of an alignment ladder, a built-in reward against a learned one, with one recipe::

    from trafficrlhf_sdk.alignment.recipe import AlignRecipe
    from trafficrlhf_sdk.evaluation import EvaluationRequest
    from trafficrlhf_sdk.pipeline import align_step, evaluate_step

    for name, reward in {"builtin": "builtin:failure-margins", "learned": "out/rm"}.items():
        aligned = align_step(f"out/{name}", AlignRecipe(model="ctg", checkpoint="ctg-4s", reward_model=reward,
                                                        align={"epochs": 20}))
        evaluate_step(f"out/{name}/eval", EvaluationRequest(model="ctg", checkpoint=aligned["folder"],
                                                            num_scenes=100, seeds=(0, 1, 2)), after=[aligned])
"""

from trafficrlhf_sdk.pipeline.stages import (
    AlignJob,
    align_step,
    align_steps,
    evaluate_step,
    generate_step,
    label_step,
    rank_step,
    reward_model_step,
)
from trafficrlhf_sdk.pipeline.step import (
    MANIFEST,
    StepConfigError,
    StepResult,
    input_differences,
    inputs_digest,
    read_manifest,
    run_step,
)

__all__ = ["MANIFEST", "AlignJob", "StepConfigError", "StepResult", "align_step", "align_steps", "evaluate_step",
           "generate_step", "input_differences", "inputs_digest", "label_step", "rank_step", "read_manifest",
           "reward_model_step", "run_step"]
