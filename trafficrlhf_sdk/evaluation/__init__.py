"""Evaluation (stage IV): the closed-loop protocol, per-scene breakdowns with paired intervals, comparison tables
and drawings of failures.

- :func:`evaluate_policy` + :class:`EvaluationConfig` -> :class:`EvaluationReport` (``protocol``);
- :func:`pooled_per_scene`, :func:`worst_scenes`, :func:`paired_change_interval`, ... (``breakdown``);
- :func:`comparison_table` and friends over saved runs (``compare``);
- :func:`first_failures`, :func:`save_failure_png` (``failures``);
- :func:`write_report`, the one-page report of an RLHF loop (``report``);
- :func:`run_evaluation` + :class:`EvaluationRequest` -> :class:`EvaluationOutcome`: scene selection, one run per
  seed (:func:`evaluate_seeds` -> :class:`SeedRuns`, their mean) and the files written (``runs``);
- :func:`render_side_by_side` + :class:`SideBySideRequest`: models side by side from the same start on the scenes
  where the base fails, as GIFs and PNG stills (``side_by_side``).
"""

from trafficrlhf_sdk.lazy import lazy_exports

_EXPORTS = {
    "EvaluationConfig": "protocol",
    "EvaluationReport": "protocol",
    "evaluate_policy": "protocol",
    "compute_metrics": "protocol",
    "run_batched": "protocol",
    "load_scene_histograms": "protocol",
    "save_scene_histograms": "protocol",
    "plot_histograms": "protocol",
    "seeds_summary": "protocol",
    "SceneShare": "breakdown",
    "SceneChange": "breakdown",
    "ChangeInterval": "breakdown",
    "pooled_per_scene": "breakdown",
    "worst_scenes": "breakdown",
    "scenes_carrying": "breakdown",
    "scene_changes": "breakdown",
    "paired_change_interval": "breakdown",
    "paired_difference_interval": "breakdown",
    "DifferenceInterval": "breakdown",
    "paired_realism_interval": "breakdown",
    "comparison_table": "compare",
    "scene_change_table": "compare",
    "change_interval_table": "compare",
    "read_results": "compare",
    "FirstFailures": "failures",
    "first_failures": "failures",
    "save_failure_png": "failures",
    "render_failures": "failures",
    "write_report": "report",
    "run_label": "compare",
    "EvaluationRequest": "runs",
    "SceneSelection": "runs",
    "EvaluationOutcome": "runs",
    "SeedRuns": "runs",
    "evaluate_seeds": "runs",
    "select_scenes": "runs",
    "load_scenes": "runs",
    "check_out_dir": "runs",
    "render_worst": "runs",
    "run_evaluation": "runs",
    "PanelSpec": "side_by_side",
    "SceneFigure": "side_by_side",
    "SideBySide": "side_by_side",
    "SideBySideOutcome": "side_by_side",
    "SideBySideRequest": "side_by_side",
    "failing_scenes": "side_by_side",
    "panel_specs": "side_by_side",
    "render_side_by_side": "side_by_side",
    "save_side_by_side_animation": "side_by_side",
    "save_side_by_side_still": "side_by_side",
    "side_by_side_frames": "side_by_side",
    "simulate_side_by_side": "side_by_side",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
