"""Model commands: `msps train | eval | predict` (torch imported only when they run)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import List, Optional

import typer

from msps_render.cli.app import app, clean_errors
from msps_render.io.png16 import PNG_OVERRIDES, PNG_RULE
from msps_render.models.steps import DEFAULT_PHOTOS, DEFAULT_RENDERED

PNG_HELP = f"force PNG values to be read as linear radiance / as sRGB-encoded. Default: {PNG_RULE}{PNG_OVERRIDES}"

# Test-time steps (models/steps.py): `--steps selfcal+netcal+refine` (or `none`); repeatable where it adds
# comparison columns (eval, bench-real).  The old per-step flags stay, hidden, for one release: they are
# mapped onto Steps in ONE place (`steps.from_flags`).
def _steps_option(columns: bool, default):
    """The --steps option: repeatable where it adds comparison columns; its default named from the registry."""
    from msps_render.models.steps import STEPS

    names = ", ".join(STEPS)
    default = f"{default}" + ("" if default.names else " (the raw network)")
    if columns:
        return typer.Option([], "--steps", metavar="STEPS", help=f"test-time steps, e.g. selfcal+netcal+refine or "
                            f"none ({names}; docs/recipes.md); repeat to compare: every method is scored under "
                            f"each (a column NAME+STEPS each). Default: {default}")
    return typer.Option(None, "--steps", metavar="STEPS", help="test-time steps applied in order, e.g. "
                        f"selfcal+netcal+refine or none ({names}; docs/recipes.md). Default: {default}")


OLD_SELFCAL = typer.Option(False, "--selfcal", hidden=True)
OLD_SEGMENTS = typer.Option(False, "--segments", hidden=True)
OLD_NETCAL = typer.Option(False, "--netcal", hidden=True)
OLD_MIRROR = typer.Option(False, "--mirror", hidden=True)
OLD_REFINE = typer.Option(False, "--refine", hidden=True)


def _steps(given: list[str], columns: bool, default, **old: bool) -> list:
    """--steps values (or the old flags) -> a list of Steps; nothing given: [default]."""
    from msps_render.errors import InputError
    from msps_render.models.steps import Steps, from_flags

    aliased = from_flags(columns, **old)
    if aliased and given:
        raise InputError("--steps", "give --steps or the old step flags (--selfcal ...), not both")
    return aliased or [Steps.parse(g) for g in given] or [default]


def _say_deprecated(columns: list, **old: bool) -> None:
    """After a command that used the old step flags succeeded: one line naming the --steps equivalent (so
    scripts move before the flags go; printed last, so a refused input keeps its one error line)."""
    flags = " ".join(f"--{k}" for k, on in old.items() if on)
    if flags:
        same = " ".join(f"--steps {s}" for s in columns)
        typer.echo(f"warning: {flags} {'is' if len(flags.split()) == 1 else 'are'} deprecated and will be "
                   f"removed; the same: {same}", err=True)


@app.command("train")
@clean_errors
def train_cmd(config: str = typer.Argument("cpu", help="model preset (models/NAME.toml) or TOML path"),
              data: List[Path] = typer.Option(..., help="training dataset directory (repeat to train "
                                              "on several as one)"),
              val: Path = typer.Option(..., help="validation dataset directory"),
              out: Path = typer.Option(..., help="run directory (checkpoints, metrics)"),
              resume: bool = typer.Option(False, help="continue the run in OUT"),
              init: Optional[Path] = typer.Option(None, help="warm start: weights of this checkpoint (a path, "
                                                  "or a shipped model's name, e.g. classic-cpu; same network), "
                                                  "fresh optimizer and schedule"),
              set_: List[str] = typer.Option([], "--set", help="override, e.g. train.max_minutes=10"),
              device: str = typer.Option("auto", help="auto (CUDA when usable, else CPU), cpu or cuda"),
              threads: Optional[int] = typer.Option(None, min=1, help="torch CPU threads"),
              smoke: bool = typer.Option(False, "--smoke", help="a short check that the whole loop works on "
                                         "your data: a few minutes on 2 cores (docs/reproducing.md)"),
              json_out: bool = typer.Option(False, "--json", help="print the end summary as JSON")):
    """Train the dual-cue network (or an ablation: --set net.mode=scn|pcn), or the classic any-light
    network (presets with kind = "classic": classic-cpu, classic-gpu) on rig datasets."""
    import torch

    from msps_render.models import classic

    if init is not None:  # a path, or a shipped checkpoint's name (models/NAME.pt, e.g. classic-cpu)
        from msps_render import resources

        init = resources.find("models", init, ".pt") or init  # not found: the loader says so, naming it
    if classic.preset_kind(config) == classic.KIND:
        from msps_render.pipeline.outdir import check_writable

        check_writable(out, "run")
        if threads:
            torch.set_num_threads(threads)
        ccfg = classic.load_classic_config(config, [*(classic.SMOKE if smoke else ()), *set_])
        r = classic.train_classic(ccfg, data if len(data) > 1 else data[0], val, out, resume=resume, device=device,
                                  init=init)
        typer.echo(json.dumps(r) if json_out else "\n".join(classic.summary_lines(r)))
        return
    from msps_render.models.presets import SMOKE, load_model_config
    from msps_render.models.train import summary_lines, train
    from msps_render.pipeline.outdir import check_writable

    check_writable(out, "run")  # an unwritable --out: one line before the data is read
    if threads:
        torch.set_num_threads(threads)
    cfg = load_model_config(config, [*(SMOKE if smoke else ()), *set_])
    r = train(cfg, data if len(data) > 1 else data[0], val, out, resume=resume, device=device, init=init)
    typer.echo(json.dumps(r) if json_out else "\n".join(summary_lines(r)))


@app.command("eval")
@clean_errors
def eval_cmd(data: Path = typer.Option(..., help="dataset directory (test set)"),
             out: Path = typer.Option(..., help="report directory"),
             checkpoint: List[str] = typer.Option([], metavar="[NAME=]PATH",
                                                  help="checkpoint PATH or NAME=PATH; repeat to compare "
                                                  "several (unnamed: net, or scn/pcn for ablations; default: "
                                                  "models/dualcue-cpu.pt)"),
             method: List[str] = typer.Option([], metavar="net|lambertian",
                                              help="net (the checkpoints) or lambertian (the baseline); "
                                              "repeatable: --method lambertian beside --checkpoint compares "
                                              "both (default: net). A rig dataset also takes lambertian-robust "
                                              "(least squares without each pixel's darkest and brightest shots)"),
             max_patches: Optional[int] = typer.Option(None, min=1, help="limit per condition"),
             steps: List[str] = _steps_option(True, DEFAULT_RENDERED),
             quiet: bool = typer.Option(False, help="no progress lines"),
             selfcal: bool = OLD_SELFCAL, refine: bool = OLD_REFINE, mirror: bool = OLD_MIRROR,
             segments: bool = OLD_SEGMENTS, netcal: bool = OLD_NETCAL):
    """Angular-error statistics, SSIM, per-object table (whole frames), robustness, for one method or
    several compared on the same frames: metrics.json, table.md (every method a column, 95 % CIs),
    error_hist.png, per_object.csv/.png (frames stored), robustness.png (sweeps)."""
    from msps_render.models.evaluate import evaluate, resolve_methods
    from msps_render.models.report import summary_lines
    from msps_render.models.rig_eval import is_rig_dataset
    from msps_render.pipeline.outdir import check_writable

    check_writable(out, "report")
    columns = _steps(steps, True, DEFAULT_RENDERED, selfcal=selfcal, segments=segments, netcal=netcal,
                     mirror=mirror, refine=refine)
    if is_rig_dataset(data):  # any rig (format-2 shards): methods that read the rig itself
        from msps_render.errors import InputError
        from msps_render.models import rig_eval

        if steps or any((selfcal, segments, netcal, mirror, refine)):
            raise InputError("--steps", f"{data} is a rig dataset: the test-time steps belong to the three-light "
                                        "dual-cue network")
        r = rig_eval.evaluate_rig(data, out, rig_eval.resolve_rig_methods(method, checkpoint,
                                                                           rig_eval.classic_reads(data)),
                                  progress=not quiet)
        typer.echo("\n".join(rig_eval.summary_lines(r)))
        typer.echo("wrote " + ", ".join(r["files"]))
        return
    r = evaluate(data, out, resolve_methods(checkpoint, method, columns), max_patches=max_patches,
                 progress=not quiet)
    for line in summary_lines(r):
        typer.echo(line)
    typer.echo("wrote " + ", ".join(r["files"]))
    _say_deprecated(columns, selfcal=selfcal, segments=segments, netcal=netcal, mirror=mirror, refine=refine)


@app.command("predict")
@clean_errors
def predict_cmd(image: Path = typer.Argument(..., help="image: EXR/HDR/NPY (linear RGB), JPG (sRGB-encoded, "
                                               "decoded to linear) or PNG (see --linear/--srgb); alpha dropped. "
                                               "Or a folder of per-light photos with their lights (DiLiGenT "
                                               "layout): classic photometric stereo with the classic network "
                                               "(default models/classic-cpu.pt) or --method lambertian"),
                out: Path = typer.Option(..., help="output path stem, dots kept: OUT.npy, OUT.png, OUT-panel.png "
                                         "(and OUT-metrics.json with --normal-gt)"),
                checkpoint: Optional[Path] = typer.Option(None, help="checkpoint (default: shipped cpu model)"),
                method: str = typer.Option("net", help="net or lambertian"),
                mask: Optional[Path] = typer.Option(None, help="mask image (default: non-zero pixels)"),
                calibration: Optional[Path] = typer.Option(None, help="calibration JSON (light_dirs or slant_deg/"
                                                "tilts_deg, crosstalk; docs/recipes.md), e.g. from `msps compose`"),
                light_dirs: Optional[str] = typer.Option(None, help="JSON 3x3, rows toward the lights"),
                crosstalk: Optional[str] = typer.Option(None, help="JSON 3x3 crosstalk matrix"),
                linear: Optional[bool] = typer.Option(None, "--linear/--srgb", help=PNG_HELP),
                normal_gt: Optional[Path] = typer.Option(None, "--normal-gt", help="ground-truth normals: .npy "
                                                         "(H, W, 3), DiLiGenT's Normal_gt.mat, or an EXR/PNG normal map ((n+1)/2-encoded; "
                                                         "signed EXR too); zero normals are left out. Adds "
                                                         "the truth and the error map to the panel and writes "
                                                         "OUT-metrics.json"),
                steps: Optional[str] = _steps_option(False, DEFAULT_PHOTOS),
                quiet: bool = typer.Option(False, help="no progress lines"),
                selfcal: bool = OLD_SELFCAL, refine: bool = OLD_REFINE, mirror: bool = OLD_MIRROR,
                segments: bool = OLD_SEGMENTS, netcal: bool = OLD_NETCAL):
    """Normal map of a whole image (overlapping 40x40 tiles, blended) or by the Lambertian baseline,
    with a panel PNG (input, prediction, and with --normal-gt the truth and the angular error)."""
    from msps_render.models.predict import load_rig, out_paths, predict_main, predict_method
    from msps_render.pipeline.outdir import check_writable

    check_writable(out.parent)
    if image.is_dir():  # a folder of per-light photos with their lights: classic photometric stereo
        from msps_render.errors import InputError
        from msps_render.models.realbench_lights import predict_folder

        if steps or any((selfcal, segments, netcal, mirror, refine)) or calibration or light_dirs or crosstalk \
                or mask or normal_gt:
            raise InputError(image, "a capture folder is read with its own light_directions.txt, "
                                    "light_intensities.txt and mask.png: --steps, --calibration, --light-dirs, "
                                    "--crosstalk, --mask and --normal-gt are for one three-light image")
        files = predict_folder(image, out, checkpoint, method)
        typer.echo("wrote " + ", ".join(map(str, files)))
        return
    (chosen,) = _steps([steps] if steps is not None else [], False, DEFAULT_PHOTOS, selfcal=selfcal,
                       segments=segments, netcal=netcal, mirror=mirror, refine=refine)
    rig = load_rig(calibration, light_dirs, crosstalk)
    files = predict_main(image, out, predict_method(method, checkpoint, chosen), rig, mask=mask, linear=linear,
                         normal_gt=normal_gt, progress=not quiet)
    if normal_gt:
        m = json.loads(out_paths(out)["metrics"].read_text())
        if m.get("n_pixels"):
            typer.echo(f"MAE {m['mae_deg']:.2f} deg, median {m['median_deg']:.2f} over {m['n_pixels']} pixels "
                       f"({m['n_left_out']} mask pixels without ground truth left out)")
        else:
            typer.echo("no pixel has both a mask and a ground-truth normal")
    typer.echo("wrote " + ", ".join(map(str, files)))
    _say_deprecated([chosen], selfcal=selfcal, segments=segments, netcal=netcal, mirror=mirror, refine=refine)


@app.command("bench-real")
@clean_errors
def bench_real_cmd(captures: List[Path] = typer.Argument(..., help="capture folders in the DiLiGenT layout "
                                                         "(e.g. pmsData/ballPNG): 001.png ..., filenames.txt, "
                                                         "light_directions.txt, light_intensities.txt, mask.png, "
                                                         "Normal_gt.mat or Normal_gt.png"),
                   out: Path = typer.Option(..., "--out", "-o", help="new (or empty) report directory"),
                   checkpoint: List[str] = typer.Option([], help="NAME=PATH of a checkpoint to score (repeat "
                                                        "to compare several; default: net = the shipped "
                                                        "models/dualcue-cpu.pt)"),
                   slant: float = typer.Option(30.0, help="target slant of the three lights (deg)"),
                   tilts: str = typer.Option("0,120,240", help="target tilts (deg, comma-separated)"),
                   crosstalk: Optional[str] = typer.Option(None, help="'paper' (default, 0.92/0.04), 'identity' "
                                                           "or a JSON 3x3 (rows: channels, columns: lights)"),
                   skip: List[str] = typer.Option([], help="leave out a capture before the nearest three are "
                                                  "chosen: FILE (e.g. 001.png, in every folder) or "
                                                  "OBJECT/FILE (one folder); repeatable"),
                   srgb: bool = typer.Option(False, "--srgb", help=f"PNG photos are sRGB-encoded. Default: {PNG_RULE}; --srgb overrides"),
                   threads: Optional[int] = typer.Option(None, min=1, help="torch CPU threads"),
                   steps: List[str] = _steps_option(True, DEFAULT_PHOTOS),
                   quiet: bool = typer.Option(False, help="no progress lines"),
                   lights: Optional[str] = typer.Option(None, metavar="all|K", help="classic photometric stereo: "
                                                        "every photo of each capture (all) or K spread evenly, "
                                                        "each with its own light; checkpoints are classic "
                                                        "networks (default: the three-light composite)"),
                   selfcal: bool = OLD_SELFCAL, refine: bool = OLD_REFINE, mirror: bool = OLD_MIRROR,
                   segments: bool = OLD_SEGMENTS, netcal: bool = OLD_NETCAL):
    """Score checkpoints and calibrated Lambertian PS on real captures (validation only: never train on
    real images).  Each folder is composed as `msps compose` does (the three captures nearest the
    layout, divided by light intensity, mixed by the crosstalk); the angular error is taken over the
    mask, leaving out zero ground-truth normals.  Writes results.json, results.md, OBJECT/error_METHOD.png,
    OBJECT/normal_METHOD.png and figure.png."""
    from msps_render.compose import parse_crosstalk
    from msps_render.errors import InputError
    from msps_render.io.staging import check_new_out
    from msps_render.models.realbench import run_bench_real, summary_table

    check_new_out(out)
    if lights is not None:  # classic N-light mode: the capture's own lights, classic networks
        from msps_render.models.realbench_lights import run_bench_real_lights, table_lines

        if lights != "all" and not lights.isdigit():
            raise InputError("--lights", f"give 'all' or a number of lights, got {lights!r}")
        if threads:
            import torch

            torch.set_num_threads(threads)
        s = run_bench_real_lights(captures, out, checkpoint, lights if lights == "all" else int(lights),
                                  progress=not quiet)
        for line in table_lines(s):
            typer.echo(line)
        typer.echo("wrote " + ", ".join(s["files"]))
        return
    columns = _steps(steps, True, DEFAULT_PHOTOS, selfcal=selfcal, segments=segments, netcal=netcal,
                     mirror=mirror, refine=refine)
    try:
        t = [float(x) for x in tilts.split(",") if x.strip()]
    except ValueError:
        raise InputError("--tilts", f"not a comma-separated list of numbers: {tilts!r}") from None
    M = parse_crosstalk(crosstalk)
    if threads:
        import torch

        torch.set_num_threads(threads)
    bench = run_bench_real(captures, out, checkpoint, columns, slant_deg=slant, tilts_deg=t, crosstalk=M, skip=skip,
                           srgb=srgb, warn=lambda w: typer.echo(f"warning: {w}", err=True), progress=not quiet)
    for line in summary_table(bench):
        typer.echo(line)
    typer.echo(f"wrote {out}/results.json, results.md, figure.png and per-object maps "
               f"({', '.join(bench.summary['objects'])})")
    _say_deprecated(columns, selfcal=selfcal, segments=segments, netcal=netcal, mirror=mirror, refine=refine)
