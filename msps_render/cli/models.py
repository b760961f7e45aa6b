"""Model commands: `msps train | eval | predict` (torch imported only when they run)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import List, Optional

import typer

from msps_render.cli.app import app, clean_errors
from msps_render.io.png16 import PNG_RULE

PNG_HELP = f"force PNG values to be read as linear radiance / as sRGB-encoded. Default: {PNG_RULE}"

# The extra columns `msps eval` and `msps bench-real` both offer: each flag adds a twin of every method
# (`msps predict` has its own wording: there the flag changes the one prediction).
ALSO_SELFCAL = typer.Option(False, "--selfcal", help="also score every method after the object-level albedo-colour "
                            "self-calibration (a column NAME+selfcal each; models/selfcal.py, docs/appearance.md)")
ALSO_REFINE = typer.Option(False, "--refine", help="also score every network with the Lambertian refinement after "
                           "it (a column NAME+refine each; objects of one albedo only; models/refine.py)")
ALSO_SEGMENTS = typer.Option(False, "--segments", help="also score every method after the object-level and then "
                             "the segment-wise albedo self-calibration, which divides out each colour region of a "
                             "textured object (a column NAME+selfcal+segments each; models/segments.py)")
ALSO_NETCAL = typer.Option(False, "--netcal", help="also score every network after the object-level "
                           "self-calibration and the albedo colour read off its own normals, predicted again "
                           "(a column NAME+selfcal+netcal each; needs whole images; models/netcal.py)")


@app.command("train")
@clean_errors
def train_cmd(config: str = typer.Argument("cpu", help="model preset (models/NAME.toml) or TOML path"),
              data: List[Path] = typer.Option(..., help="training dataset directory (repeat to train "
                                              "on several as one)"),
              val: Path = typer.Option(..., help="validation dataset directory"),
              out: Path = typer.Option(..., help="run directory (checkpoints, metrics)"),
              resume: bool = typer.Option(False, help="continue the run in OUT"),
              init: Optional[Path] = typer.Option(None, help="warm start: weights of this checkpoint "
                                                  "(same network), fresh optimizer and schedule"),
              set_: List[str] = typer.Option([], "--set", help="override, e.g. train.max_minutes=10"),
              device: str = typer.Option("auto", help="auto (CUDA when usable, else CPU), cpu or cuda"),
              threads: Optional[int] = typer.Option(None, help="torch CPU threads"),
              smoke: bool = typer.Option(False, "--smoke", help="a short check that the whole loop works on "
                                         "your data: a few minutes on 2 cores (docs/reproducing.md)"),
              json_out: bool = typer.Option(False, "--json", help="print the end summary as JSON")):
    """Train the dual-cue network (or an ablation: --set net.mode=scn|pcn)."""
    import torch

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
                                              "both (default: net)"),
             max_patches: Optional[int] = typer.Option(None, help="limit per condition"),
             selfcal: bool = ALSO_SELFCAL,
             refine: bool = ALSO_REFINE,
             mirror: bool = typer.Option(False, "--mirror", help="also score every network averaged with its "
                                         "prediction of the mirrored image (NAME+mirror; rigs symmetric about an "
                                         "image axis, as the paper's; models/symmetry.py)"),
             segments: bool = ALSO_SEGMENTS,
             netcal: bool = ALSO_NETCAL):
    """Angular-error statistics, SSIM, per-object table (whole frames), robustness, for one method or
    several compared on the same frames: metrics.json, table.md (every method a column, 95 % CIs),
    error_hist.png, per_object.csv/.png (frames stored), robustness.png (sweeps)."""
    from msps_render.models.evaluate import evaluate, resolve_methods
    from msps_render.models.report import summary_lines
    from msps_render.pipeline.outdir import check_writable

    check_writable(out, "report")
    r = evaluate(data, out, max_patches=max_patches, methods=resolve_methods(checkpoint, method, selfcal, refine, mirror,
                                                                               segments, netcal))
    for line in summary_lines(r):
        typer.echo(line)
    typer.echo("wrote " + ", ".join(r["files"]))


@app.command("predict")
@clean_errors
def predict_cmd(image: Path = typer.Argument(..., help="image: EXR/HDR/NPY (linear RGB), JPG (sRGB-encoded, "
                                               "decoded to linear) or PNG (see --linear/--srgb); alpha dropped"),
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
                                                         "(H, W, 3) or EXR/PNG normal map ((n+1)/2-encoded; "
                                                         "signed EXR too); zero normals are left out. Adds "
                                                         "the truth and the error map to the panel and writes "
                                                         "OUT-metrics.json"),
                selfcal: bool = typer.Option(False, "--selfcal", help="first divide out the object's albedo "
                                             "colour when one uniform colour fits it clearly better than grey "
                                             "(needs the rig: --calibration or the paper's lights; "
                                             "models/selfcal.py)"),
                refine: bool = typer.Option(False, "--refine", help="refine the network's normals by the "
                                            "Lambertian closed form where the image agrees with it (objects "
                                            "of one albedo; needs the rig; models/refine.py)"),
                mirror: bool = typer.Option(False, "--mirror", help="average the network's prediction with its "
                                            "prediction of the mirrored image (2x the time; needs a rig symmetric "
                                            "about an image axis, as the paper's; models/symmetry.py)"),
                segments: bool = typer.Option(False, "--segments", help="after --selfcal (implied), cut a "
                                              "textured object at its colour edges and divide out each "
                                              "region's own albedo (needs the rig; models/segments.py)"),
                netcal: bool = typer.Option(False, "--netcal", help="after --selfcal (implied), read the "
                                            "object's albedo colour off the network's own normals, divide it "
                                            "out and predict again (2x the time; models/netcal.py)")):
    """Normal map of a whole image (overlapping 40x40 tiles, blended) or by the Lambertian baseline,
    with a panel PNG (input, prediction, and with --normal-gt the truth and the angular error)."""
    from msps_render.models.predict import out_paths, predict_main
    from msps_render.pipeline.outdir import check_writable

    check_writable(out.parent)
    files = predict_main(image, out, checkpoint, method, mask, calibration, light_dirs, crosstalk,
                         linear=linear, normal_gt=normal_gt, selfcal=selfcal,
                         refine=refine, mirror=mirror, segments=segments, netcal=netcal)
    if normal_gt:
        m = json.loads(out_paths(out)["metrics"].read_text())
        if m.get("n_pixels"):
            typer.echo(f"MAE {m['mae_deg']:.2f} deg, median {m['median_deg']:.2f} over {m['n_pixels']} pixels "
                       f"({m['n_left_out']} mask pixels without ground truth left out)")
        else:
            typer.echo("no pixel has both a mask and a ground-truth normal")
    typer.echo("wrote " + ", ".join(map(str, files)))


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
                   srgb: bool = typer.Option(False, "--srgb", help=f"PNG photos are sRGB-encoded. Default: {PNG_RULE}"),
                   threads: Optional[int] = typer.Option(None, help="torch CPU threads"),
                   selfcal: bool = ALSO_SELFCAL,
                   refine: bool = ALSO_REFINE,
                   segments: bool = ALSO_SEGMENTS,
                   netcal: bool = ALSO_NETCAL):
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
    try:
        t = [float(x) for x in tilts.split(",") if x.strip()]
    except ValueError:
        raise InputError("--tilts", f"not a comma-separated list of numbers: {tilts!r}") from None
    M = parse_crosstalk(crosstalk)
    if threads:
        import torch

        torch.set_num_threads(threads)
    bench = run_bench_real(captures, out, checkpoint, slant, t, M, skip, srgb,
                           warn=lambda w: typer.echo(f"warning: {w}", err=True), selfcal=selfcal,
                           refine=refine, segments=segments, netcal=netcal)
    for line in summary_table(bench):
        typer.echo(line)
    typer.echo(f"wrote {out}/results.json, results.md, figure.png and per-object maps "
               f"({', '.join(bench.summary['objects'])})")
