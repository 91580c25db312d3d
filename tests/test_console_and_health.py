"""Output a person reads: progress off a terminal is one plain line, and unhealthy PPO figures are flagged."""

from __future__ import annotations

import pytest

from trafficrlhf_sdk.alignment.health import HEALTH_RANGES, health_warnings
from trafficrlhf_sdk.console import PlainProgress, interactive, progress


def test_off_a_terminal_progress_is_one_plain_line(capsys: pytest.CaptureFixture[str]) -> None:
    assert not interactive()  # pytest captures stdout and stderr: neither is a terminal
    bar = progress(range(4), desc="simulating", unit="batch")
    assert isinstance(bar, PlainProgress)
    assert list(bar) == [0, 1, 2, 3]
    manual = progress(total=3, desc="align ctg", unit="epoch")
    manual.update(1)
    manual.set_postfix(reward="0.123")
    manual.update(2)
    manual.close()
    manual.close()  # closing twice writes nothing more
    out, err = capsys.readouterr()
    assert out == "" and "\r" not in err
    lines = err.splitlines()
    assert len(lines) == 2
    assert lines[0].startswith("simulating: 4/4 batches in ")
    assert lines[1].startswith("align ctg: 3/3 epochs in ") and lines[1].endswith("(reward 0.123)")


def test_health_warnings_flag_only_figures_above_their_range() -> None:
    assert HEALTH_RANGES["approx_kl"][1] == 0.2 and HEALTH_RANGES["clip_fraction"][1] == 0.5
    assert health_warnings({"epoch": 3.0, "approx_kl": 0.05, "clip_fraction": 0.34}) == []
    assert health_warnings({"epoch": 3.0, "approx_kl": 0.0, "clip_fraction": 0.0}) == []
    lines = health_warnings({"epoch": 4.0, "approx_kl": 4.1, "clip_fraction": 0.6})
    assert len(lines) == 2
    assert lines[0].startswith("epoch 4: approx_kl 4.1 is above its typical range 0-0.2") and "target_kl" in lines[0]
    assert "clip_fraction 0.6" in lines[1] and "docs/how-to/align.md" in lines[1]
