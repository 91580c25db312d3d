"""``trafficrlhf experiment paper``: table formatting, the comparison with the paper's directions, the
configuration, and the quick form end to end on real scenes."""

from __future__ import annotations

import json
import math
import os

import pytest
from click.testing import CliRunner
from hypothesis import given
from hypothesis import strategies as st
from pydantic import ValidationError

from trafficrlhf_sdk.experiments import EXPECTED, PUBLISHED, SOURCE, TABLES, PaperConfig, compare_change
from trafficrlhf_sdk.experiments.published import published_change
from trafficrlhf_sdk.experiments.report import clean_json, direction_rows, fmt, markdown_table, plot_bars, write_result

finite = st.floats(-1e6, 1e6, allow_nan=False)


def test_markdown_table_formats_cells_and_checks_widths() -> None:
    table = markdown_table(["a", "b", "c"], [[0.123456, None, "x"], [float("nan"), 3, True]])
    assert table.splitlines() == ["| a | b | c |", "|---|---|---|", "| 0.1235 | n/a | x |", "| n/a | 3.0000 | yes |"]
    with pytest.raises(ValueError, match="2 cells for 3 headers"):
        markdown_table(["a", "b", "c"], [[1, 2]])
    assert fmt(0.5, 2) == "0.50" and fmt(None) == "n/a" and fmt("CTG") == "CTG"


@given(metric=st.sampled_from(sorted(EXPECTED)), base=finite, aligned=finite)
def test_property_compare_change_agrees_only_with_the_expected_sign(metric: str, base: float, aligned: float) -> None:
    result = compare_change(metric, base, aligned)
    assert result["change"] == aligned - base
    expected = EXPECTED[metric].direction
    if expected == 0:
        assert result["agrees"] is None
    else:
        assert result["agrees"] == ((aligned - base) * expected > 0)
    if base:
        assert result["relative"] == pytest.approx((aligned - base) / abs(base))
    else:
        assert result["relative"] is None


def test_compare_change_with_a_missing_value_and_the_directions() -> None:
    assert compare_change("failure_rate", None, 0.1)["agrees"] is None
    assert EXPECTED["realism_ctg"].direction == -1 and EXPECTED["realism_meta"].direction == 1
    assert EXPECTED["reward_cost"].direction == -1 and EXPECTED["failure_rate"].direction == 0
    assert "2309.00709" in SOURCE
    # the paper's own numbers (Tables 1-4), filed by the labels the experiments give their comparisons
    assert PUBLISHED["no_collision: CTG → CTG + RM"]["failure_rate"] == (0.271, 0.054)
    assert published_change("no_collision: CTG → CTG + RM", "failure_rate") == pytest.approx(-0.8007, abs=1e-4)
    assert published_change("BITS: without → with RM", "reward_cost") == pytest.approx((9.5 - 12.4) / 12.4)
    assert published_change("speed_limit: CTG → CTG + RM", "reward_cost") is None  # Table 1 prints no cost
    assert published_change("no such comparison", "failure_rate") is None
    rows = direction_rows([("CTG: without → with RM", {"failure_rate": 0.1}, {"failure_rate": 0.05})],
                          ["failure_rate"])
    assert rows[0]["relative"] == pytest.approx(-0.5) and rows[0]["paper_relative"] == pytest.approx(-0.8007, abs=1e-4)


def test_published_numbers_are_filed_under_the_labels_the_tables_compare() -> None:
    """The paper's numbers reach a table only through the comparison labels paper.py builds; a label changed on
    one side would silently print "n/a" instead of the paper's change."""
    import inspect

    from trafficrlhf_sdk.experiments import GUIDANCES, paper

    cfg = PaperConfig()
    labels = {f"{g}: CTG → CTG + RM" for g in GUIDANCES}
    labels |= {f"{m}: without → with RM" for m in ("CTG", "BITS", "TrafficGen")}
    labels |= {f"CTG → CTG + RM ({variant})" for variant in cfg.table3_groups}
    labels |= {f"{m} → + RM ({backbone})" for m in ("BITS", "TrafficGen") for backbone in cfg.backbones}
    assert set(PUBLISHED) == labels
    source = inspect.getsource(paper)  # the label patterns this test rebuilds are the ones the tables use
    for pattern in ('f"{guidance}: CTG → CTG + RM"', 'f"{m}: without → with RM"', 'f"CTG → CTG + RM ({variant})"',
                    'f"{model_name} → + RM ({backbone})"'):
        assert pattern in source, pattern


@given(value=st.recursive(st.floats() | st.integers() | st.text(max_size=3) | st.none(),
                          lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=3), inner,
                                                                                       max_size=3), max_leaves=10))
def test_property_clean_json_is_strict_json(value: object) -> None:
    text = json.dumps(clean_json(value), allow_nan=False)  # raises on NaN or infinity
    assert json.loads(text) is not None or clean_json(value) is None


def test_direction_rows_and_written_result(tmp_path) -> None:
    rows = direction_rows([("CTG", {"realism_ctg": 0.1, "failure_rate": 0.2}, {"realism_ctg": 0.08,
                                                                                "failure_rate": float("nan")})],
                          ["realism_ctg", "failure_rate", "reward_cost"])
    assert [r["metric"] for r in rows] == ["realism_ctg", "failure_rate", "reward_cost"]
    assert rows[0]["agrees"] is True and rows[0]["relative"] == pytest.approx(-0.2)
    assert rows[2]["agrees"] is None  # reward cost not measured
    result = {"title": "T", "command": "trafficrlhf experiment paper --out DIR --only table2", "seed": 0,
              "rollouts": 2, "scenes": 4, "threads": 1, "wall_time_s": 1.5, "value": float("inf")}
    paths = write_result(str(tmp_path / "t"), result, markdown_table(["x"], [[1.0]]), rows, ["a note"])
    saved = json.loads(open(paths[0]).read())
    assert saved["value"] is None and saved["paper_source"] == SOURCE and len(saved["comparison"]) == 3
    text = open(paths[1]).read()
    assert "| CTG | realism dev. (paper) | 0.1000 | 0.0800 | -20.0 % | n/a | lower | yes |" in text
    assert "- a note" in text and "--only table2" in text
    png = plot_bars(str(tmp_path / "t.png"), ["A", "A + RM"], {"failure_rate": [0.2, None]}, "t")
    assert open(png, "rb").read(8) == b"\x89PNG\r\n\x1a\n"


def test_config_forbids_unknown_keys_and_quick_is_small() -> None:
    with pytest.raises(ValidationError):
        PaperConfig(sceens=10)
    with pytest.raises(ValidationError):
        PaperConfig(only=("table9",))
    full, quick = PaperConfig(), PaperConfig.quick()
    assert full.only == TABLES and full.scenes == 100 and len(full.guidances) == 5
    assert quick.label == "quick" and quick.scenes <= 4 and quick.rollouts >= 2  # the meta-metric path runs
    assert quick.align_overrides.epochs == 1 and quick.only == TABLES
    assert PaperConfig.quick(scenes=3).scenes == 3
    for name, field in PaperConfig.model_fields.items():
        assert field.description, name


def test_cli_rejects_an_unknown_table_before_any_work(tmp_path) -> None:
    from trafficrlhf_sdk.cli import get_cli

    result = CliRunner().invoke(get_cli(), ["experiment", "paper", "--out", str(tmp_path / "x"), "--only",
                                            "table1,table9"])
    assert result.exit_code != 0 and "table9" in result.output
    assert not (tmp_path / "x").exists()


@pytest.mark.slow
@pytest.mark.data
def test_quick_form_writes_every_table_with_finite_numbers(data_root: str, tmp_path) -> None:
    from trafficrlhf_sdk.cli import get_cli

    out = tmp_path / "paper"
    result = CliRunner().invoke(get_cli(), ["experiment", "paper", "--out", str(out), "--quick", "--threads", "1"])
    assert result.exit_code == 0, (result.output, result.exception)
    for name in TABLES:
        for suffix in ("json", "md", "png"):
            assert (out / name / f"result.{suffix}").is_file(), (name, suffix)
        assert (out / name / "result.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        saved = json.loads((out / name / "result.json").read_text())
        assert saved["label"] == "quick" and saved["wall_time_s"] > 0 and "--quick" in saved["command"]
        assert saved["paper_source"] == SOURCE and saved["rows"]

    def numbers(row: dict, keys: tuple[str, ...]) -> list[float]:
        values = [row[k] for k in keys]
        assert all(isinstance(v, float) and math.isfinite(v) for v in values), row
        return values

    metrics = ("realism_ctg", "realism_body", "realism_meta", "failure_rate", "reward_cost")
    table1 = json.loads((out / "table1" / "result.json").read_text())
    assert [(r["guidance"], r["model"]) for r in table1["rows"][:2]] == [("speed_limit", "CTG"),
                                                                         ("speed_limit", "CTG + RM")]
    assert len(table1["rows"]) == 10 and len(table1["comparison"]) == 25
    for row in table1["rows"]:
        realism, _body, meta, failure, cost = numbers(row, metrics)
        assert 0 <= failure <= 1 and 0 < meta <= 1 and realism >= 0 and 0 <= cost <= 20
    table2 = json.loads((out / "table2" / "result.json").read_text())
    assert [r["model"] for r in table2["rows"]] == ["CTG", "CTG + RM", "BITS", "BITS + RM", "TrafficGen",
                                                    "TrafficGen + RM"]
    for row in table2["rows"]:
        numbers(row, metrics)
    # CTG in Table 2 is the same evaluation as CTG with the same guidance in Table 1 (cached, not rerun)
    ctg = next(r for r in table1["rows"] if r["guidance"] == "no_collision" and r["model"] == "CTG")
    assert table2["rows"][0]["failure_rate"] == ctg["failure_rate"]
    table3 = json.loads((out / "table3" / "result.json").read_text())
    assert [r["variant"] for r in table3["rows"]] == ["CTG (not fine-tuned)", "CTG + RM, encoder",
                                                      "CTG + RM, decoder", "CTG + RM, full"]
    assert [r["groups"] for r in table3["rows"][1:]] == ["encoder", "decoder", "encoder,decoder"]
    for row in table3["rows"]:
        numbers(row, metrics)
    table4 = json.loads((out / "table4" / "result.json").read_text())
    assert [r["backbone"] for r in table4["rows"]] == ["", "CTG encoder", "TrafficGen encoder"] * 2
    for path in table4["reward_models"].values():
        assert json.loads(open(os.path.join(path, "config.json")).read())["architecture"] in ("ctg_mlp",
                                                                                             "trafficgen_mcg")
    for row in table4["rows"]:
        numbers(row, metrics[:4])
        assert len(row["costs"]) == 2 and all(math.isfinite(v) for v in row["costs"].values())
    figure3 = json.loads((out / "figure3" / "result.json").read_text())
    assert [r["contexts"] for r in figure3["rows"]] == [4, 8] and figure3["test_pairs"] > 0
    for run in figure3["runs"]:
        assert 0 <= run["accuracy_all_pairs"] <= 1
    summary = (out / "summary.md").read_text()
    assert all(f"Table {i}" in summary for i in range(1, 5)) and "Figure 3" in summary
    # a rerun finds every step done: nothing is evaluated, aligned, generated or trained, no table rewritten
    written = {name: (out / name / "result.json").read_text() for name in TABLES}
    again = CliRunner().invoke(get_cli(), ["experiment", "paper", "--out", str(out), "--quick"])
    assert again.exit_code == 0, again.output
    steps = [line for line in again.output.splitlines() if line.endswith("skipped")]
    assert sum("every step done before" in line for line in steps) == len(TABLES)
    assert not [line for line in again.output.splitlines()
                if line.startswith(("evaluating", "aligned", "campaign", "trained", "figure 3:"))]
    assert {name: (out / name / "result.json").read_text() for name in TABLES} == written
    # other settings for the same folder are refused, naming the setting, before anything is redone
    other = CliRunner().invoke(get_cli(), ["experiment", "paper", "--out", str(out), "--quick", "--scenes", "3",
                                           "--only", "table1"])
    assert other.exit_code != 0 and "num_scenes: 4 -> 3" in str(other.exception)
