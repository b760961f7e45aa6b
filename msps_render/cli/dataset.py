"""Dataset commands: `msps render | verify | inspect | preview | card`."""
from __future__ import annotations

import json
from pathlib import Path
from typing import List, Optional

import typer

from msps_render.cli.app import app, clean_errors
from msps_render.errors import InputError, not_a_dataset


@app.command("render")
@clean_errors
def render_cmd(config: str = typer.Argument(..., help="preset name (scenes/NAME.toml) or TOML path"),
               out: Path = typer.Option(..., "--out", "-o", help="dataset directory"),
               seed: Optional[int] = typer.Option(None, min=0, help="root seed (overrides dataset.seed)"),
               workers: int = typer.Option(1, min=1, help="local worker processes (or Dask LocalCluster size, "
                                                   "or Slurm jobs)"),
               scheduler: Optional[str] = typer.Option(None, help="'dask-local', 'slurm' or tcp://host:8786"),
               resume: bool = typer.Option(False, help="finish the dataset in --out with the config stored in its "
                                                       "dataset.json (no --set needed; one that differs is refused)"),
               force: bool = typer.Option(False, help="delete the finished shards in --out (the toolkit's files "
                                                      "only) and render this config from scratch"),
               set_: List[str] = typer.Option([], "--set", help="override, e.g. lights.slant_deg=25"),
               variant: Optional[str] = typer.Option(None, help="Mitsuba variant"),
               threads: Optional[int] = typer.Option(None, min=1, help="render threads per worker (default: cores / workers)"),
               recycle_after: int = typer.Option(0, min=0, help="replace a local worker after N shards (0: never)"),
               quiet: bool = typer.Option(False, help="no progress bar"),
               space_check: bool = typer.Option(True, "--space-check/--no-space-check",
                                                help="before rendering, refuse when the shards will not fit "
                                                     "in the free space (estimate: `msps config show --probe`)"),
               partition: Optional[str] = typer.Option(None, help="Slurm: partition (scheduler.slurm.partition)"),
               cores: Optional[int] = typer.Option(None, help="Slurm: CPUs per worker job"),
               memory: Optional[str] = typer.Option(None, help="Slurm: memory per worker job, e.g. 4GB"),
               walltime: Optional[str] = typer.Option(None, help="Slurm: time limit per job, e.g. 04:00:00"),
               sbatch: List[str] = typer.Option([], "--sbatch", help="Slurm: extra sbatch option (repeatable), "
                                                                      "e.g. --sbatch=--qos=low")):
    """Render a dataset of HDF5 patch shards."""
    from msps_render.cli._signals import nothing_written_yet

    with nothing_written_yet():  # Mitsuba's import takes seconds; a Ctrl-C inside it is one line, exit 130
        import mitsuba  # noqa: F401
    from msps_render.pipeline.config import load_config
    from msps_render.pipeline.run import config_difference, render_dataset, resume_config
    from msps_render.pipeline.slurm import with_flags

    overrides = list(set_) + ([f"dataset.seed={seed}"] if seed is not None else [])
    cfg = load_config(config, overrides)
    note = ""
    if resume:  # finish what the dataset was started with: no --set needs retyping
        stored = resume_config(out, overrides)
        if stored is not None:
            diff = config_difference(stored.model_dump(mode="json"), cfg.model_dump(mode="json"))
            if diff:
                note = f"; resumed with the config stored in dataset.json, not {config} as given ({diff})"
            stored.scheduler = cfg.scheduler  # where to run is not part of the dataset (not stored, not hashed)
            cfg = stored
    cfg.scheduler.slurm = with_flags(cfg.scheduler.slurm, scheduler, partition=partition, cores=cores,
                                     memory=memory, walltime=walltime, sbatch=sbatch)
    m = render_dataset(cfg, out, workers=workers, scheduler=scheduler, resume=resume, force=force,
                       variant=variant, threads=threads, progress=not quiet,
                       recycle_after=recycle_after or None, space_check=space_check)
    card = f"; card: {out / 'card.png'}" if m["complete"] and (out / "card.png").is_file() else ""
    typer.echo(f"{out}: {len(m['shards'])} shards, {m['n_patches']} patches, complete={m['complete']}{card}{note}")


@app.command("verify")
@clean_errors
def verify_cmd(root: Path = typer.Argument(..., help="dataset directory")):
    """Check every shard: complete, checksums, finite, unit normals, consistent masks. Exit 1 if bad."""
    from msps_render.dataset.verify import dataset_status

    st = dataset_status(root, deep=True)
    if not st.ok:
        for line in st.lines():
            typer.echo(line, err=True)
        raise typer.Exit(1)
    typer.echo(f"{root}: all {st.recorded} shards OK, complete, {st.n_patches} patches")


@app.command("inspect")
@clean_errors
def inspect_cmd(path: Path = typer.Argument(..., help="dataset directory or shard .h5")):
    """Summary table of a dataset or one shard."""
    from rich.console import Console
    from rich.table import Table

    from msps_render.dataset import read_manifest, shard_summary
    from msps_render.dataset.reader import shard_errors
    from msps_render.dataset.verify import dataset_status

    con = Console()
    if path.is_dir():
        m = read_manifest(path)
        if m is None:
            raise InputError(path, "no dataset.json here")
        st = dataset_status(path, deep=False)  # the same definition as verify and train, without hashing
        t = Table(title=f"{path} (config {m.get('config_hash', '?')[:12]}, seed {m.get('seed')}, "
                        f"complete={st.complete})")
        for c in ("shard", "condition", "frames", "patches", "render s", "wall s"):
            t.add_column(c)
        for name, e in sorted(m["shards"].items()):
            t.add_row(name, e.get("condition", ""), str(e["n_frames"]), str(e["n_patches"]),
                      f"{e.get('render_seconds', 0):.2f}", f"{e.get('wall_seconds', 0):.2f}")
        con.print(t)
        con.print(f"total patches: {sum(e['n_patches'] for e in m['shards'].values())}; "
                  f"versions: {json.dumps(m.get('versions', {}))}")
        if not st.ok:
            for line in st.lines(limit=5):
                typer.echo(line, err=True)
            raise typer.Exit(1)
    elif path.is_file():
        with shard_errors(path):
            info = shard_summary(path)
        t = Table(title=str(path))
        t.add_column("dataset")
        t.add_column("shape")
        t.add_column("dtype")
        t.add_column("compression")
        for n, (shape, dt, comp) in info.pop("datasets").items():
            t.add_row(n, str(shape), dt, str(comp))
        con.print(t)
        con.print({k: v for k, v in info.items()})
    else:
        raise InputError(path, "not found")


@app.command("preview")
@clean_errors
def preview_cmd(root: Path = typer.Argument(..., help="dataset directory"),
                out: Path = typer.Option(..., "--out", "-o", help="PNG contact sheet"),
                n: int = typer.Option(8, min=1, help="number of samples (whole frames if stored, else patches); at least one "
                                              "per sweep condition"),
                tile: int = typer.Option(160, min=160, max=1024, help="tile size in px (image, normal, mask)"),
                cols: int = typer.Option(2, min=1, max=16, help="samples per row"),
                labels: bool = typer.Option(True, "--labels/--no-labels",
                                            help="label each sample: shard/frame, shape, materials, condition")):
    """Contact sheet of labelled samples (image | normal map | mask) + slant/material/coverage distributions.
    Deterministic: the same dataset gives the same PNG."""
    from msps_render.pipeline.outdir import check_writable
    from msps_render.pipeline.preview import preview_dataset

    if not (root / "dataset.json").is_file():
        raise not_a_dataset(root)
    check_writable(out.parent)
    typer.echo(f"wrote {preview_dataset(root, out, n, tile=tile, cols=cols, labels=labels)}")


@app.command("card")
@clean_errors
def card_cmd(root: Path = typer.Argument(..., help="dataset directory"),
             out: Optional[Path] = typer.Option(None, "--out", "-o",
                                                help="card PNG (default DIR/card.png); the JSON goes beside it")):
    """Dataset card: counts, versions and coverage histograms (slant, tilts, environment, crosstalk,
    materials, albedo, textures, shapes, patch coverage) as one PNG and one JSON.
    `msps render` writes DIR/card.png and DIR/card.json itself when a dataset is complete."""
    from msps_render.dataset.card import write_card
    from msps_render.pipeline.outdir import check_writable

    if not (root / "dataset.json").is_file():
        raise not_a_dataset(root)
    if out is not None and out.suffix.lower() != ".png":
        raise InputError(out, "--out must be a .png path (the JSON is written beside it)")
    check_writable(out.parent if out is not None else root)
    png, js = write_card(root, out)
    typer.echo(f"wrote {png} and {js}")
