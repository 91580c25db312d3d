"""Recipe, loop and experiment files are validated in full when they load: every shipped TOML loads, and a
misspelled key in a nested table fails at once (before any work, no output folder), naming the key's path, with
a one-line error from the CLI."""

from __future__ import annotations

import time
import tomllib
from pathlib import Path

import pytest
from pydantic import BaseModel, ValidationError

from trafficrlhf_sdk.alignment.recipe import AlignRecipe
from trafficrlhf_sdk.cli.app import EXIT_USER_ERROR, main
from trafficrlhf_sdk.config_files import load_config, set_fields
from trafficrlhf_sdk.errors import DataFormatError
from trafficrlhf_sdk.experiments.config import PaperConfig
from trafficrlhf_sdk.experiments.ladder import LadderConfig
from trafficrlhf_sdk.loop import RLHFConfig

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = sorted(p for folder in ("scripts", "docs", "reference_models", "benchmarks")
                 for p in (ROOT / folder).rglob("*.toml") if p.name != "pyproject.toml")


def config_kind(path: Path) -> type[BaseModel]:
    """Which model a TOML file holds: a recipe names its reward model, an experiment or ladder file sets
    PaperConfig or LadderConfig fields a loop has not, anything else is a loop."""
    data = tomllib.loads(path.read_text(encoding="utf-8"))
    if "reward_model" in data:
        return AlignRecipe
    if set(data) - set(RLHFConfig.model_fields) and set(data) <= set(PaperConfig.model_fields):
        return PaperConfig
    if set(data) - set(RLHFConfig.model_fields) and set(data) <= set(LadderConfig.model_fields):
        return LadderConfig
    return RLHFConfig


def test_the_shipped_files_were_found() -> None:
    names = {p.relative_to(ROOT).as_posix() for p in SHIPPED}
    assert {"scripts/main.toml", "docs/recipes/ctg-rlhf.toml", "reference_models/baselines/bits/recipe.toml"} <= names


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_shipped_toml_loads(path: Path) -> None:
    kind = config_kind(path)
    data = tomllib.loads(path.read_text(encoding="utf-8"))
    # a ladder config without a recipe runs the one `--model` names (the CLI's default: CTG's)
    default = {"recipe": "docs/recipes/ctg-ladder.toml"} if kind is LadderConfig and "recipe" not in data else {}
    config = AlignRecipe.load(str(path)) if kind is AlignRecipe else load_config(kind, str(path), **default)
    dumped = config.model_dump()
    for table in ("align", "reward"):  # nested tables keep exactly the keys the file sets
        if isinstance(data.get(table), dict):
            assert set(dumped[table]) == set(data[table])
            assert set_fields(getattr(config, table)) == dumped[table]


def test_a_nested_section_dumps_only_what_was_set_and_round_trips() -> None:
    config = RLHFConfig(align={"learning_rate": 1e-3, "groups": ["steer"]}, reward={"max_epochs": 6})
    assert config.model_dump(mode="json")["align"] == {"learning_rate": 1e-3, "groups": ["steer"]}
    assert config.model_dump()["reward"] == {"max_epochs": 6}
    assert RLHFConfig(**config.model_dump()) == config
    assert RLHFConfig().model_dump()["reward"] == {"ensemble_size": 3, "max_epochs": 30}
    paper = PaperConfig.quick()
    assert PaperConfig(**paper.model_dump(mode="json")) == paper
    assert paper.align_overrides.epochs == 1 and set_fields(paper.figure3_reward) == {"max_epochs": 2}


def _misspelled(tmp_path: Path, source: str, old: str, new: str) -> str:
    text = (ROOT / source).read_text(encoding="utf-8")
    assert old in text, f"{source} no longer has {old!r}; pick another key to misspell"
    path = tmp_path / "misspelled.toml"
    path.write_text(text.replace(old, new, 1), encoding="utf-8")
    return str(path)


CASES = [  # (command, shipped file or None for a written one, text, misspelled text, path the error must name)
    ("rlhf", "scripts/main.toml", "\nlearning_rate =", "\nlearnig_rate =", "align.learnig_rate"),
    ("rlhf", "docs/recipes/ctg-rlhf.toml", "\nmax_epochs =", "\nmax_epoch =", "reward.max_epoch"),
    ("align", "reference_models/baselines/bits/recipe.toml", "\nepochs =", "\nepochz =", "align.epochz"),
    ("experiment paper", None, "", 'align_bits = "docs/recipes/bits-rm.tom"\n', "align_bits"),
    ("experiment paper", None, "", '[backbones."CTG encoder"]\narchitecure = "ctg_mlp"\n',
     "backbones.CTG encoder.architecure"),
    ("experiment paper", None, "", "scenes = 4\n[align_overrides]\nepoch = 1\n", "align_overrides.epoch"),
]


@pytest.fixture(scope="module", autouse=True)
def _imported() -> None:
    """What the commands import before they load a file, imported once, so the timing below measures the
    loading and not Python's first imports."""
    import trafficrlhf_sdk.experiments.paper  # noqa: F401


@pytest.mark.parametrize(("command", "source", "old", "new", "key"), CASES, ids=[c[4] for c in CASES])
def test_a_misspelled_nested_key_fails_at_load_naming_it(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                         command: str, source: str | None, old: str, new: str,
                                                         key: str) -> None:
    if source is None:
        path = tmp_path / "experiment.toml"
        path.write_text(new, encoding="utf-8")
        config_path = str(path)
    else:
        config_path = _misspelled(tmp_path, source, old, new)
    out = tmp_path / "out"
    began = time.perf_counter()
    with pytest.raises(SystemExit) as stopped:
        main([*command.split(), "--config", config_path, "--out", str(out)])
    elapsed = time.perf_counter() - began
    err = capsys.readouterr().err
    assert stopped.value.code == EXIT_USER_ERROR, err
    assert key in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert elapsed < 2.0, f"failing took {elapsed:.2f} s"
    assert not out.exists()  # nothing started


def test_load_config_names_the_file_and_every_problem(tmp_path: Path) -> None:
    path = tmp_path / "loop.toml"
    path.write_text('rounds = 0\n[align]\nlearnig_rate = 1\n[reward]\nensemble_size = "three"\n', encoding="utf-8")
    with pytest.raises(DataFormatError) as caught:
        load_config(RLHFConfig, str(path))
    message = str(caught.value)
    assert str(path) in message and "rounds" in message and "align.learnig_rate" in message
    assert "reward.ensemble_size" in message


def test_an_experiment_fails_at_load_on_a_misspelled_key_in_a_recipe_it_reads(tmp_path: Path) -> None:
    recipe = _misspelled(tmp_path, "docs/recipes/bits-rm.toml", "\nepochs =", "\nepochz =")
    with pytest.raises(ValidationError) as caught:
        PaperConfig(align_bits=recipe)
    assert "align_bits" in str(caught.value) and "align.epochz" in str(caught.value)
    assert PaperConfig(align_bits="docs/recipes/bits-rm.toml").align_bits == "docs/recipes/bits-rm.toml"


def test_a_recipe_without_a_reward_takes_the_command_lines(tmp_path: Path) -> None:
    """`align --config` with only an [align] table and `--reward-model` on the command line: the command line
    fills (and overrides) the file's fields before it is validated."""
    from trafficrlhf_sdk.alignment.recipe import AlignRecipe
    from trafficrlhf_sdk.errors import DataFormatError

    path = tmp_path / "only_align.toml"
    path.write_text('model = "ctg"\n[align]\nepochs = 3\n')
    recipe = AlignRecipe.load(str(path), reward_model="builtin:failure", checkpoint=None)
    assert recipe.reward_model == "builtin:failure" and recipe.align.epochs == 3 and recipe.model == "ctg"
    assert AlignRecipe.load(str(path), model="bits", reward_model="builtin:failure").model == "bits"
    with pytest.raises(DataFormatError, match="reward_model"):
        AlignRecipe.load(str(path))
