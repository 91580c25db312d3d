"""Bundled checkpoints run with the options their card was measured with, and say so when loaded."""

from __future__ import annotations

import json
import shutil

import pytest

from trafficrlhf_sdk.plugins import registry


def _bundled(name: str) -> str:
    if name not in registry("pretrained").names():
        pytest.skip(f"bundled checkpoint {name!r} is not installed")
    return str(registry("pretrained").get(name))


@pytest.mark.parametrize("name", ["ctg-aligned", "ctg-baseline", "bits-baseline", "trafficgen-baseline"])
def test_cards_measured_with_guidance_record_it(name: str) -> None:
    from trafficrlhf_sdk.plugins import checkpoint_options

    folder = _bundled(name)
    assert checkpoint_options(folder) == {"guidance": "no_collision"}
    with open(f"{folder}/README.md", encoding="utf-8") as handle:
        assert "no_collision" in handle.read()  # the guidance the card's figures were measured with


def test_from_pretrained_applies_the_card_guidance_and_says_so(capsys: pytest.CaptureFixture[str]) -> None:
    from trafficrlhf_sdk import from_pretrained

    _bundled("ctg-aligned")
    model = from_pretrained("ctg-aligned", seed=0)
    assert model.options.guidance == "no_collision"
    err = capsys.readouterr().err
    assert "note: checkpoint 'ctg-aligned' runs with the options its card was measured with" in err
    assert "guidance='no_collision'" in err
    # an explicit guidance wins, and "none" turns the recorded one off; neither is announced
    assert from_pretrained("ctg-aligned", guidance="no_offroad").options.guidance == "no_offroad"
    assert not from_pretrained("ctg-aligned", guidance="none").options.guidance
    assert "note:" not in capsys.readouterr().err


def test_a_checkpoint_without_recorded_options_loads_as_before(tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    from trafficrlhf_sdk import from_pretrained

    folder = tmp_path / "copy"
    shutil.copytree(_bundled("ctg-aligned"), folder)
    config = json.loads((folder / "config.json").read_text())
    del config["options"]
    (folder / "config.json").write_text(json.dumps(config))
    assert not from_pretrained(str(folder), seed=0).options.guidance
    assert "note:" not in capsys.readouterr().err
    config["options"] = ["no_collision"]
    (folder / "config.json").write_text(json.dumps(config))
    with pytest.raises(Exception, match="`options` is"):
        from_pretrained(str(folder))
