"""Per-scene breakdowns: which scenes carry the failure rate, which changed between two models."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from trafficrlhf_sdk.errors import DataFormatError
from trafficrlhf_sdk.evaluation.breakdown import (
    paired_change_interval,
    paired_realism_interval,
    pooled_per_scene,
    realism_deviation_draws,
    scene_changes,
    scenes_carrying,
    worst_scenes,
)


def _result(values, seed=0, ids=None, agents=None, model="m"):  # type: ignore[no-untyped-def]
    ids = ids or [f"scene-{i:04d}" for i in range(len(values))]
    return {"metrics": {"failure_rate": float(np.mean([v for v in values if v is not None]))},
            "metadata": {"model": model, "seed": seed, "scene_ids": ids},
            "per_scene": {"failure_rate": values, "collision_rate": values, "offroad_rate": [0.0] * len(values),
                          "controlled_agents": agents or [2] * len(values)},
            "simulation_time_s": 1.0, "num_scenes": len(values), "num_controlled_agents": 2 * len(values)}


def test_pooling_averages_seeds_and_drops_scenes_without_agents() -> None:
    pooled = pooled_per_scene([_result([0.5, None, 0.0]), _result([1.0, None, 0.5], seed=1)])
    assert pooled == {"scene-0000": (2, 0.75), "scene-0002": (2, 0.25)}


def test_pooling_refuses_other_scenes_and_old_results() -> None:
    with pytest.raises(DataFormatError, match="different scenes"):
        pooled_per_scene([_result([0.5, 0.0]), _result([0.5, 0.0], ids=["a", "b"])])
    old = _result([0.5])
    del old["per_scene"]
    with pytest.raises(DataFormatError, match="re-run `trafficrlhf evaluate --out`"):
        pooled_per_scene([old])


def test_worst_scenes_match_a_numpy_reference() -> None:
    rng = np.random.default_rng(0)
    values = rng.random(40) * (rng.random(40) < 0.4)
    pooled = pooled_per_scene([_result(values.tolist())])
    rows = worst_scenes(pooled)
    order = sorted(range(40), key=lambda i: (-values[i], f"scene-{i:04d}"))
    assert [r.scene_id for r in rows] == [f"scene-{i:04d}" for i in order]
    np.testing.assert_allclose([r.cumulative_share for r in rows], np.cumsum(values[order]) / values.sum())
    # the fewest scenes reaching 80 %: the first index where the numpy running share reaches it, plus one
    assert scenes_carrying(pooled, 0.8) == int(np.argmax(np.cumsum(values[order]) / values.sum() >= 0.8)) + 1
    assert len(worst_scenes(pooled, 3)) == 3


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(0, 1), min_size=1, max_size=30), st.randoms())
def test_shares_are_a_distribution_whatever_the_scene_order(values, rand) -> None:  # type: ignore[no-untyped-def]
    pooled = pooled_per_scene([_result(values)])
    rows = worst_scenes(pooled)
    if sum(values) > 0:
        assert rows[-1].cumulative_share == pytest.approx(1.0)
        assert all(a.value >= b.value for a, b in zip(rows, rows[1:]))
        assert 1 <= scenes_carrying(pooled, 0.5) <= scenes_carrying(pooled, 0.8) <= len(values)
    else:
        assert scenes_carrying(pooled, 0.8) == 0
    items = list(pooled.items())
    rand.shuffle(items)
    assert worst_scenes(dict(items)) == rows  # ties broken by scene id, not by input order


def test_scene_changes_rank_by_absolute_change() -> None:
    before = {"a": (1, 0.0), "b": (3, 0.5), "c": (2, 0.2), "only-before": (1, 1.0)}
    after = {"a": (1, 1.0), "b": (3, 0.25), "c": (2, 0.2)}
    rows = scene_changes(before, after)
    assert [(r.scene_id, r.change) for r in rows] == [("a", 1.0), ("b", -0.25), ("c", 0.0)]
    with pytest.raises(ValueError, match="fraction"):
        scenes_carrying(before, 0.0)


def test_compare_lists_the_scenes_that_changed_most(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.cli import get_cli

    runs = {"base_s0": _result([0.5, 0.0, 1.0], model="base"), "base_s1": _result([0.5, 0.0, 0.0], 1, model="base"),
            "new_s0": _result([0.0, 0.5, 0.5], model="new")}
    for name, result in runs.items():
        (tmp_path / name).mkdir()
        (tmp_path / name / "results.json").write_text(json.dumps(result))
    folders = [str(tmp_path / name) for name in runs]
    out = CliRunner().invoke(get_cli(), ["compare", *folders, "--scene-changes", "2"])
    assert out.exit_code == 0, out.output
    assert "failure_rate per scene, base -> new: 1 scenes lower, 1 higher, 1 unchanged" in out.output
    assert "| scene-0000 | 2 | 0.5000 | 0.0000 | -0.5000 |" in out.output
    assert "| scene-0001 | 2 | 0.0000 | 0.5000 | +0.5000 |" in out.output
    assert "scene-0002" not in out.output  # unchanged (0.5 both), outside the top 2
    single = CliRunner().invoke(get_cli(), ["compare", folders[0], "--scene-changes", "2"])
    assert single.exit_code != 0 and "two policies" in str(single.exception)


def _pooled(values) -> dict[str, tuple[int, float]]:  # type: ignore[no-untyped-def]
    return {f"scene-{i:04d}": (2, float(v)) for i, v in enumerate(values)}


def test_paired_interval_matches_scipy_bootstrap() -> None:
    from scipy.stats import bootstrap

    rng = np.random.default_rng(3)
    before = rng.random(100) * (rng.random(100) < 0.5)
    after = before * rng.uniform(0.0, 0.8, 100) + 0.02 * (rng.random(100) < 0.2)
    ci = paired_change_interval(_pooled(before), _pooled(after), resamples=20_000, seed=1, target=-0.7)

    def ratio(x, y, axis=-1):  # type: ignore[no-untyped-def]
        return y.sum(axis) / x.sum(axis) - 1.0

    ref = bootstrap((before, after), ratio, paired=True, vectorized=True, n_resamples=20_000,
                    confidence_level=0.95, method="percentile", random_state=np.random.default_rng(2))
    assert ci.change == pytest.approx(after.sum() / before.sum() - 1.0)
    assert ci.before == pytest.approx(before.mean()) and ci.after == pytest.approx(after.mean())
    # two independent Monte-Carlo estimates of the same percentiles
    assert ci.low == pytest.approx(ref.confidence_interval.low, abs=0.01)
    assert ci.high == pytest.approx(ref.confidence_interval.high, abs=0.01)
    assert ci.low < ci.change < ci.high and ci.scenes == 100 and ci.resamples == 20_000
    assert 0.0 <= ci.share_meeting_target <= 1.0  # type: ignore[operator]


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(0.01, 1), min_size=2, max_size=40), st.floats(0.1, 3.0), st.integers(0, 2**16))
def test_paired_interval_scales_with_the_second_evaluation(values, factor, seed) -> None:  # type: ignore[no-untyped-def]
    same = paired_change_interval(_pooled(values), _pooled(values), resamples=200, seed=seed)
    assert same.change == pytest.approx(0.0, abs=1e-12)
    assert same.low == pytest.approx(0.0, abs=1e-12) and same.high == pytest.approx(0.0, abs=1e-12)
    scaled = paired_change_interval(_pooled(values), _pooled([factor * v for v in values]), resamples=200, seed=seed)
    # the same draws: every resampled ratio is multiplied by the factor
    assert 1 + scaled.change == pytest.approx(factor)
    assert 1 + scaled.low == pytest.approx(factor, rel=1e-9) and 1 + scaled.high == pytest.approx(factor, rel=1e-9)


def test_paired_interval_refuses_what_it_cannot_measure() -> None:
    with pytest.raises(ValueError, match="level"):
        paired_change_interval(_pooled([0.1, 0.2]), _pooled([0.1, 0.2]), level=1.0)
    with pytest.raises(ValueError, match="resamples"):
        paired_change_interval(_pooled([0.1, 0.2]), _pooled([0.1, 0.2]), resamples=10)
    with pytest.raises(DataFormatError, match="share 1 scene"):
        paired_change_interval(_pooled([0.1, 0.2]), {"scene-0000": (2, 0.1)})
    with pytest.raises(DataFormatError, match="relative change is undefined"):
        paired_change_interval(_pooled([0.0, 0.0]), _pooled([0.1, 0.2]))


def test_compare_interval_prints_the_change_with_its_interval(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.cli import get_cli

    rng = np.random.default_rng(0)
    base = rng.random(30)
    runs = {"base_s0": _result(base.tolist(), model="base"), "base_s1": _result((base * 0.9).tolist(), 1, model="base"),
            "new_s0": _result((base * 0.3).tolist(), model="new")}
    for name, result in runs.items():
        (tmp_path / name).mkdir()
        (tmp_path / name / "results.json").write_text(json.dumps(result))
    folders = [str(tmp_path / name) for name in runs]
    out = CliRunner().invoke(get_cli(), ["compare", *folders, "--interval", "--target", "-60"])
    assert out.exit_code == 0, out.output
    assert "base -> new (2 / 1 seed(s)); 95 % paired bootstrap interval over scenes" in out.output
    # pooled base = 0.95 x base, new = 0.3 x base: -68.4 % on every draw, so the interval is that point
    assert "| failure rate | " in out.output and "-68.4 % | -68.4 % to -68.4 % | 1.00 |" in out.output
    assert "| off-road rate | 0.0000 | 0.0000 | n/a: 0 before | | |" in out.output
    lonely = CliRunner().invoke(get_cli(), ["compare", *folders, "--target", "-70"])
    assert lonely.exit_code == 2 and "--target -70 only acts with --interval or --plot" in lonely.output
    lonely = CliRunner().invoke(get_cli(), ["compare", *folders, "--level", "0.9"])
    assert lonely.exit_code == 2 and "--level 0.9 only acts with --interval" in lonely.output
    # seeds given out of order are listed in seed order
    reordered = CliRunner().invoke(get_cli(), ["compare", folders[1], folders[0], folders[2]])
    assert "base, seeds 0 / 1" in reordered.output, reordered.output


def _counts(rng, scenes=12, bins=20, empty=()):  # type: ignore[no-untyped-def]
    run = {}
    for q in ("lon_acc", "lat_acc", "jerk", "pace"):
        run[q] = {side: rng.integers(0, 6, size=(scenes, bins)) for side in ("simulated", "logged")}
        for scene in empty:
            run[q]["simulated"][scene] = 0
    return run


def test_realism_draws_match_scipy_on_the_drawn_scenes() -> None:
    from scipy.stats import wasserstein_distance

    from trafficrlhf_sdk.metrics.realism import QUANTITIES, SPECS

    rng = np.random.default_rng(3)
    run = _counts(rng, empty=(4,))
    weights = rng.multinomial(12, np.full(12, 1 / 12), size=5).astype(float)
    draws = realism_deviation_draws(run, np.vstack([np.ones((1, 12)), weights]))
    for row, w in zip(draws, np.vstack([np.ones((1, 12)), weights])):
        distances = []
        for q in QUANTITIES:
            spec = SPECS[q]
            centres = spec.low + (np.arange(spec.num_bins) + 0.5) * (spec.high - spec.low) / spec.num_bins
            picked = np.repeat(np.arange(12), w.astype(int))  # the drawn scenes, repeats included
            shares = {}
            for side in ("simulated", "logged"):
                c = run[q][side][picked].astype(float)
                totals = c.sum(1, keepdims=True)
                shares[side] = np.where(totals > 0, c / np.maximum(totals, 1), 0).mean(0)
            distances.append(wasserstein_distance(centres, centres, shares["logged"], shares["simulated"]))
        assert row == pytest.approx(np.mean(distances), abs=1e-12)


@settings(max_examples=25, deadline=None)
@given(scale=st.integers(1, 9), scene=st.integers(0, 11), seed=st.integers(0, 2**16))
def test_realism_weighs_each_scene_once_whatever_its_sample_count(scale, scene, seed) -> None:  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(seed)
    run = _counts(rng)
    scaled = {q: {side: c.copy() for side, c in sides.items()} for q, sides in run.items()}
    for q in scaled:
        scaled[q]["simulated"][scene] *= scale
    w = rng.multinomial(12, np.full(12, 1 / 12), size=20).astype(float)
    np.testing.assert_allclose(realism_deviation_draws(scaled, w), realism_deviation_draws(run, w), atol=1e-12)
    same = paired_realism_interval([run], [run], resamples=200)
    assert same.change == 0.0 and same.low == 0.0 and same.high == 0.0


def test_realism_interval_pools_seeds_and_refuses_what_it_cannot_measure() -> None:
    rng = np.random.default_rng(5)
    before, after = [_counts(rng), _counts(rng)], [_counts(rng)]
    ci = paired_realism_interval(before, after, resamples=500, level=0.9)
    ones = np.ones((1, 12))
    x = np.mean([realism_deviation_draws(run, ones)[0] for run in before])
    assert ci.before == pytest.approx(x) and ci.change == pytest.approx(ci.after / x - 1)
    assert ci.low <= ci.change <= ci.high and ci.scenes == 12 and ci.level == 0.9
    with pytest.raises(DataFormatError, match="different numbers of scenes"):
        paired_realism_interval(before, [_counts(rng, scenes=11)], resamples=200)
    missing = _counts(rng)
    del missing["jerk"]
    with pytest.raises(DataFormatError, match="lack 'jerk'"):
        paired_realism_interval(before, [missing], resamples=200)
    with pytest.raises(ValueError, match="level"):
        paired_realism_interval(before, after, level=1.0)


def test_scene_histograms_round_trip_and_a_bad_file_is_named(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk.evaluation.protocol import load_scene_histograms, save_scene_histograms

    run = _counts(np.random.default_rng(0))
    path = save_scene_histograms({"ctg": run}, str(tmp_path / "h.npz"))
    loaded = load_scene_histograms(path)
    for q, sides in run.items():
        for side, counts in sides.items():
            np.testing.assert_array_equal(loaded["ctg"][q][side], counts)
    (tmp_path / "bad.npz").write_text("not a zip")
    with pytest.raises(DataFormatError, match=r"bad\.npz: not a per-scene histogram archive"):
        load_scene_histograms(str(tmp_path / "bad.npz"))
