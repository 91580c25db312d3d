"""``trafficrlhf feedback ...``: campaigns, annotators, admins, settings, gold items, priorities, synthetic
labeling, export, renders, status.

``feedback serve`` (the browser app) is added by the ``trafficrlhf-annotation-web`` plugin through the
``register_commands(cli)`` hook; it finds this group as ``cli.commands["feedback"]``.
"""

from __future__ import annotations

import json
import os
from typing import Any

import click

from trafficrlhf_sdk.cli.app import cli, parse_key_values, ray_options
from trafficrlhf_sdk.config_files import read_text
from trafficrlhf_sdk.errors import DatabaseFileError, TrafficRLHFError

__all__ = ["feedback"]

db_option = click.option("--db", "db_path", required=True, type=click.Path(dir_okay=False, path_type=str),
                         help="The feedback database (SQLite file).")
campaign_option = click.option("--campaign", required=True, help="Campaign name.")


def _store(db_path: str) -> Any:
    """The existing feedback database at ``db_path``; only `feedback create` makes a new one."""
    from trafficrlhf_sdk.feedback.store import FeedbackStore

    if not os.path.isfile(db_path):
        raise DatabaseFileError(f"`--db` {db_path!r}: no such feedback database; create it (with a campaign) "
                                f"by `trafficrlhf feedback create --db {db_path} --name NAME --model MODEL`, or "
                                "check the path.")
    if os.path.getsize(db_path) == 0:  # SQLite would take it for a new database and write a schema into it
        raise DatabaseFileError(f"`--db` {db_path!r} is an empty file, not a feedback database; pass the file "
                                "`trafficrlhf feedback create` made.")
    return FeedbackStore(db_path)


def _parse_options(pairs: tuple[str, ...]) -> dict[str, Any]:
    return dict(parse_key_values(pairs, "--model-option"))


@cli.group("feedback")
def feedback() -> None:
    """Collect human feedback: best-of-N realism choices over traffic futures (stage I of TrafficRLHF)."""


@feedback.command("create")
@db_option
@click.option("--name", required=True, help="Campaign name (unique in the database).")
@click.option("--model", "models", multiple=True,
              help="Registered traffic model (required for a new campaign). Repeat it to mix models in one set: "
                   "candidate k comes from the (k mod M)-th model.")
@click.option("--guidance", default=None, help="Guidance spec for models that accept one.")
@click.option("--model-option", "model_options", multiple=True, metavar="KEY=VALUE",
              help="Extra traffic-model option (JSON value), repeatable, e.g. checkpoint=dir.")
@click.option("--source", default="nuscenes_pred", show_default=True, help="Registered scenario source.")
@click.option("--split", default="val", show_default=True, help="Split of the source.")
@click.option("--root", default=None, help="Data directory of the source.")
@click.option("--scenes", "num_contexts", type=click.IntRange(min=1), default=None,
              help="K: the first K long-enough scenes of the split [default: 10].")
@click.option("--scene-id", "scene_ids", multiple=True, help="A scene to use (repeatable) instead of --scenes.")
@click.option("--candidates", "num_candidates", type=click.IntRange(2, 9), default=5, show_default=True,
              help="N candidate futures per context.")
@click.option("--seconds", "candidate_seconds", type=click.FloatRange(min=0.5, max=30), default=5.0,
              show_default=True, help="Length of each candidate (s).")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True, help="Campaign seed.")
@click.option("--labels-per-item", type=click.IntRange(min=1), default=None,
              help="Annotators per item (default: every annotator labels every item).")
@click.option("--extend", is_flag=True, help="Add contexts to an existing campaign (its stored settings are kept).")
@ray_options("the candidates' generation")
def create_command(db_path: str, name: str, models: tuple[str, ...], guidance: str | None,
                   model_options: tuple[str, ...],
                   source: str, split: str, root: str | None, num_contexts: int | None, scene_ids: tuple[str, ...],
                   num_candidates: int, candidate_seconds: float, seed: int, labels_per_item: int | None,
                   extend: bool, workers: int, ray_address: str | None) -> None:
    """Generate N candidates for each of K contexts with a traffic model and store them (with the log)."""
    from trafficrlhf_sdk.feedback.campaign import CampaignConfig, create_campaign, extend_campaign
    from trafficrlhf_sdk.feedback.store import open_store
    from trafficrlhf_sdk.parallel import ExecutionConfig

    execution = ExecutionConfig(workers=workers, ray_address=ray_address)
    report_line = lambda scene: click.echo(f"  + {scene}")  # noqa: E731
    if not extend and not models:
        raise click.UsageError("--model is required for a new campaign (or pass --extend).")
    with open_store(db_path, must_exist=extend) as store:  # a failure removes a database it created
        if extend:
            report = extend_campaign(store, name, scene_ids=list(scene_ids) or None, num_contexts=num_contexts,
                                     root=root, on_context=report_line, execution=execution)
        else:
            slots = [models[k % len(models)] for k in range(num_candidates)] if len(models) > 1 else None
            config = CampaignConfig(
                name=name, model=models[0], candidate_models=slots, guidance=guidance,
                model_options=_parse_options(model_options), source=source,
                split=split, root=root, scene_ids=list(scene_ids) or None, num_contexts=num_contexts or 10,
                num_candidates=num_candidates, candidate_seconds=candidate_seconds, seed=seed,
                labels_per_item=labels_per_item)
            click.echo(f"campaign {name!r}: {', '.join(slots) if slots else config.model} "
                       f"({config.guidance or 'no guidance'}), N = {num_candidates}, "
                       f"{candidate_seconds:g} s candidates")
            report = create_campaign(store, config, on_context=report_line, execution=execution)
        items = store.counts(report.campaign)["items"]
    skipped = f", {len(report.skipped)} already present" if report.skipped else ""
    if report.empty:
        skipped += f", {len(report.empty)} left out with no vehicle to judge at their start ({', '.join(report.empty)})"
    click.echo(f"added {len(report.added)} contexts{skipped}; campaign {name!r} now has {items} items in {db_path}")


@feedback.group("annotator")
def annotator_group() -> None:
    """Manage annotators and their tokens."""


@annotator_group.command("add")
@db_option
@click.argument("name")
def annotator_add(db_path: str, name: str) -> None:
    """Create annotator NAME and print its token (shown once; only a hash is stored)."""
    _, token = _store(db_path).add_annotator(name)
    click.echo(token)


@annotator_group.command("token")
@db_option
@click.argument("name")
def annotator_token(db_path: str, name: str) -> None:
    """Issue a new token for NAME (the old one stops working) and print it."""
    click.echo(_store(db_path).new_token(name))


@annotator_group.command("list")
@db_option
def annotator_list(db_path: str) -> None:
    """List annotators."""
    for a in _store(db_path).annotators():
        click.echo(f"{a.name}\tcreated {a.created_at}{'' if a.active else ' (revoked)'}")


@annotator_group.command("deactivate")
@db_option
@click.argument("name")
def annotator_deactivate(db_path: str, name: str) -> None:
    """Revoke NAME's token and release their open items (`annotator token NAME` reactivates with a new token)."""
    _store(db_path).set_active(name, False)
    click.echo(f"{name}: deactivated")


@annotator_group.command("requalify")
@db_option
@campaign_option
@click.argument("name")
def annotator_requalify(db_path: str, campaign: str, name: str) -> None:
    """Let NAME take CAMPAIGN's qualification again (e.g. after missing a gold item): their gold answers there are
    removed and the gold items served again; their other labels stay."""
    store = _store(db_path)
    removed = store.reset_qualification(name, store.campaign(campaign))
    click.echo(f"{name}: qualification for {campaign!r} starts again ({removed['labels']} gold answers removed)")


@feedback.command("admin")
@db_option
@click.argument("name")
def admin_command(db_path: str, name: str) -> None:
    """Create (or re-key) campaign owner NAME and print the admin token for the app's /admin page."""
    click.echo(_store(db_path).add_admin(name))


@feedback.command("settings")
@db_option
@campaign_option
@click.option("--guidelines", "guidelines_path", type=click.Path(dir_okay=False, exists=True, path_type=str),
              default=None, help="Markdown file of guidelines shown at sign-in and on demand.")
@click.option("--no-guidelines", is_flag=True, help="Remove the guidelines.")
@click.option("--playback-required/--playback-optional", default=None,
              help="Whether the future must play through before a choice is accepted.")
@click.option("--gold-rate", type=click.FloatRange(0, 0.5), default=None, help="Share of gold items served.")
@click.option("--qualification-gold", type=click.IntRange(0, 100), default=None,
              help="N: gold items an annotator answers first; their labels count once they pass.")
@click.option("--qualification-accuracy", type=click.FloatRange(0, 1), default=None,
              help="Share of the N qualification items to answer right.")
@click.option("--lease-seconds", type=click.FloatRange(min=1, max=86400), default=None,
              help="How long an opened item stays reserved (with labels_per_item).")
@click.option("--allow-tie/--no-tie", default=None, help="Offer 'equally realistic'.")
def settings_command(db_path: str, campaign: str, guidelines_path: str | None, no_guidelines: bool,
                     playback_required: bool | None, gold_rate: float | None, qualification_gold: int | None,
                     qualification_accuracy: float | None, lease_seconds: float | None,
                     allow_tie: bool | None) -> None:
    """Show or change a campaign's annotation settings (only the options given change)."""
    changes: dict[str, Any] = {k: v for k, v in {
        "playback_required": playback_required, "gold_rate": gold_rate, "qualification_gold": qualification_gold,
        "qualification_accuracy": qualification_accuracy, "lease_seconds": lease_seconds, "allow_tie": allow_tie,
    }.items() if v is not None}
    if guidelines_path and no_guidelines:
        raise click.UsageError("pass --guidelines FILE or --no-guidelines, not both.")
    if guidelines_path:
        changes["guidelines"] = read_text(guidelines_path, "--guidelines")
    if no_guidelines:
        changes["guidelines"] = None
    store = _store(db_path)
    camp = store.update_settings(campaign, **changes) if changes else store.campaign(campaign)
    shown = camp.settings.model_dump()
    if shown["guidelines"]:
        shown["guidelines"] = f"{len(shown['guidelines'])} characters of Markdown"
    click.echo(json.dumps(shown, indent=2))


@feedback.command("gold")
@db_option
@campaign_option
@click.option("--count", type=click.IntRange(1, 1000), required=True, help="Gold items to add.")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True,
              help="Seed of the broken futures and of the answer's position.")
def gold_command(db_path: str, campaign: str, count: int, seed: int) -> None:
    """Add gold items (the logged future against broken copies of it) built from the campaign's items."""
    from trafficrlhf_sdk.feedback.gold import add_gold_items

    store = _store(db_path)
    added = add_gold_items(store, campaign, count, seed)
    total = store.counts(store.campaign(campaign))["gold_items"]
    click.echo(f"added {len(added)} gold items to {campaign!r}; it has {total} in all")


@feedback.command("prioritize")
@db_option
@campaign_option
@click.option("--ranking", "ranking_path", required=True, type=click.Path(dir_okay=False, exists=True, path_type=str),
              help="Text file of item ids, most wanted first (e.g. by reward-model disagreement), one per line.")
def prioritize_command(db_path: str, campaign: str, ranking_path: str) -> None:
    """Serve the items of a ranking first, in its order (the others follow as before)."""
    from trafficrlhf_sdk.feedback.selection import priorities_from_ranking

    lines = [line.strip() for line in read_text(ranking_path, "--ranking").splitlines()
             if line.strip() and not line.startswith("#")]
    try:
        ids = [int(line) for line in lines]
    except ValueError as exc:
        raise click.BadParameter(f"every line must be an item id; {exc}", param_hint="--ranking") from exc
    store = _store(db_path)
    n = store.set_priorities(store.campaign(campaign), priorities_from_ranking(ids))
    click.echo(f"{n} items of {campaign!r} ranked; they are served first, in the file's order")


@feedback.command("label")
@db_option
@campaign_option
@click.option("--synthetic", is_flag=True, help="Label with a stand-in annotator (people use `feedback serve`).")
@click.option("--annotator", "name", default="synthetic", show_default=True, help="Annotator name.")
@click.option("--profile", type=click.Choice(["attentive", "safety", "flow", "hurried"]), default=None,
              help="A stand-in annotator profile (what it weighs, how often it errs); the options below override it.")
@click.option("--beta", type=float, default=None,
              help="Rationality (inverse temperature on realism 0..1); 0 means perfectly rational [default: 20].")
@click.option("--epsilon", type=click.FloatRange(0, 1), default=None, help="Mistake rate [default: 0].")
@click.option("--none-threshold", type=click.FloatRange(0, 1), default=None,
              help="'None realistic' when the best realism is at or below this [default: 0.35].")
@click.option("--skip-rate", type=click.FloatRange(0, 1), default=0.0, show_default=True, help="Random skips.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the annotator's draws.")
@click.option("--limit", type=click.IntRange(min=1), default=None, help="Label at most this many items.")
def label_command(db_path: str, campaign: str, synthetic: bool, name: str, profile: str | None, beta: float | None,
                  epsilon: float | None, none_threshold: float | None, skip_rate: float, seed: int,
                  limit: int | None) -> None:
    """Label a campaign's items through the same store API as people."""
    from trafficrlhf_sdk.feedback.synthetic import PROFILES, SyntheticAnnotator, SyntheticAnnotatorConfig

    if not synthetic:
        raise click.UsageError("only --synthetic labeling runs here; people label in the browser "
                               "(`trafficrlhf feedback serve`).")
    base = PROFILES[profile] if profile else SyntheticAnnotatorConfig()
    changes: dict[str, object] = {"skip_rate": skip_rate, "seed": seed}
    if beta is not None:
        changes["beta"] = beta if beta > 0 else None
    if epsilon is not None:
        changes["epsilon"] = epsilon
    if none_threshold is not None:
        changes["none_threshold"] = none_threshold
    config = SyntheticAnnotatorConfig(**{**base.model_dump(), **changes})
    counts = SyntheticAnnotator(_store(db_path), name, config).label(campaign, limit=limit)
    click.echo(f"{name}: labeled {counts['labeled']} items ({counts['none_realistic']} 'none realistic', "
               f"{counts['ties']} ties), skipped {counts['skipped']}")


@feedback.command("export")
@db_option
@campaign_option
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=str),
              help="Directory for preferences.safetensors + metadata.json.")
@click.option("--val-fraction", type=click.FloatRange(0, 1, max_open=True), default=0.2, show_default=True,
              help="Share of contexts (never pairs) held out for validation.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the train/val split.")
@click.option("--only", type=click.Choice(["all", "human", "synthetic"]), default="all", show_default=True,
              help="Which labels to export.")
@click.option("--ties", type=click.Choice(["drop", "soft"]), default="drop", show_default=True,
              help="'Equally realistic' labels: no pair, or soft 0.5 pairs between all candidates.")
@click.option("--include-unqualified", is_flag=True,
              help="Also export labels of annotators who have not passed the campaign's qualification.")
def export_command(db_path: str, campaign: str, out_dir: str, val_fraction: float, seed: int, only: str,
                   ties: str, include_unqualified: bool) -> None:
    """Export a PreferenceDataset (N-1 pairs per choice; logged ≻ each candidate on 'none')."""
    from trafficrlhf_sdk.feedback.preference import export_preferences

    sources = ("human", "synthetic") if only == "all" else (only,)
    dataset = export_preferences(_store(db_path), campaign, val_fraction=val_fraction, seed=seed, sources=sources,
                                 ties=ties, qualified_only=not include_unqualified)  # type: ignore[arg-type]
    dataset.save(out_dir)
    n_val = sum(s == "val" for s in dataset.context_split)
    click.echo(f"{len(dataset)} pairs from {dataset.num_choices} choices over {dataset.num_contexts} contexts "
               f"({dataset.num_contexts - n_val} train / {n_val} val) -> {out_dir}")


@feedback.command("render")
@db_option
@campaign_option
@click.option("--item", "item_id", type=int, default=None, help="Item (context) id; default: the first item.")
@click.option("--out", "out_path", required=True, type=click.Path(dir_okay=False, path_type=str),
              help="Output: .png (strip) or .gif / .mp4 (animation).")
@click.option("--with-log", is_flag=True, help="Add the logged future as a last panel.")
@click.option("--step", type=int, default=None, help="Time step of the PNG strip (default: late in the window).")
def render_command(db_path: str, campaign: str, item_id: int | None, out_path: str, with_log: bool,
                   step: int | None) -> None:
    """Render a candidate set as a PNG strip or an animation for sharing."""
    from trafficrlhf_sdk.feedback.render import save_candidate_animation, save_candidate_strip

    store = _store(db_path)
    camp = store.campaign(campaign)
    if item_id is None:
        keys = store.context_keys(camp)
        if not keys:
            raise TrafficRLHFError(f"campaign {campaign!r} has no items yet.")
        item_id = keys[0]["id"]
    record = store.load_context(item_id, camp)
    if out_path.lower().endswith(".png"):
        save_candidate_strip(record, out_path, step=step, include_logged=with_log)
    else:
        save_candidate_animation(record, out_path, include_logged=with_log)
    click.echo(f"item {item_id} ({record.scene_id}) -> {out_path}")


@feedback.command("status")
@db_option
@click.option("--campaign", default=None, help="One campaign (default: all).")
@click.option("--json", "as_json", is_flag=True, help="Print JSON.")
def status_command(db_path: str, campaign: str | None, as_json: bool) -> None:
    """Campaigns with their items, labels, skips and agreement."""
    from trafficrlhf_sdk.feedback.agreement import campaign_agreement

    store = _store(db_path)
    camps = [store.campaign(campaign)] if campaign else store.campaigns()
    rows = []
    for camp in camps:
        agreement = campaign_agreement(store, camp)
        rows.append({"campaign": camp.name, "model": camp.model, "guidance": camp.guidance, "seed": camp.seed,
                     "candidates": camp.num_candidates, "sdk_version": camp.sdk_version, **store.counts(camp),
                     "fleiss_kappa": agreement["fleiss_kappa"], "pairwise_agreement": agreement["pairwise_agreement"],
                     "items_multi": agreement["items_multi"]})
    if as_json:
        click.echo(json.dumps(rows, indent=2))
        return
    if not rows:
        click.echo(f"no campaigns in {db_path}")
    fmt = lambda v: "n/a" if v is None else f"{v:.3f}"  # noqa: E731
    for r in rows:
        click.echo(f"{r['campaign']}: model {r['model']} ({r['guidance'] or 'no guidance'}), N = {r['candidates']}, "
                   f"{r['items']} items (+{r['gold_items']} gold), {r['labels']} labels ({r['none_realistic']} none, "
                   f"{r['ties']} ties) by {r['annotators']} annotators, {r['skips']} skips, {r['items_over_cap']} "
                   f"items over the cap; Fleiss' kappa {fmt(r['fleiss_kappa'])}, pairwise agreement "
                   f"{fmt(r['pairwise_agreement'])} over {r['items_multi']} items with >= 2 labels")
