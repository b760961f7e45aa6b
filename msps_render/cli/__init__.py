"""`msps` command line: a thin typer layer over the pipeline stages, one module per command group
(`scene`, `dataset`, `config`, `models`, `workflows`), all registered on the one `app` of `cli.app`.

Every command turns `InputError` into one line on stderr and exit code 1, and
writes nothing until its inputs have been validated.  torch and Mitsuba are
imported only inside the commands that need them.
"""
from msps_render.cli._signals import nothing_written_yet

with nothing_written_yet():
    from msps_render.cli import scene, dataset, config, models, workflows  # noqa: F401, I001, E402  (registers the commands, in help order)
    from msps_render.cli.app import app, clean_errors, fail  # noqa: E402

__all__ = ["app", "clean_errors", "fail", "main"]


def main() -> None:  # pragma: no cover
    app()
