"""One stage of one case of ``comreg batch``, as a Snakemake job runs it::

    python -m comreg_core.batch.stage --case C --stage register --status S.json \\
        [--after UPSTREAM.json ...] [--fresh PATH ...] -- register US --ct CT --out DIR ...

It runs the ``comreg`` command after ``--`` in this process (the CLI's own function, with its
checks and one-line errors) and writes the stage's **status file**, the rule's declared output:

``{"case", "stage", "status": "ok" | "failed", "failed_stage", "error", "exit_code",
"seconds", "command"}``

A command that fails (exit status 2 for an input it refuses, 1 for a bug) is recorded there
with its one-line error, and this process still exits 0: the case is done, as failed, and
Snakemake goes on with the other cases; a rerun does not repeat it unless its inputs change.
When a stage it reads from (``--after``) failed, the command is not run and that failure is
passed on (``failed_stage`` names where it happened). A job that is killed (Ctrl-C, a cluster's
time limit) writes no status, so Snakemake counts it failed and runs it again next time.
``--fresh`` paths (the stage's own outputs, inside the case folder) are removed first.
"""

from __future__ import annotations

import argparse
import io
import json
import shutil
import signal
import sys
import threading
import time
from contextlib import redirect_stderr
from pathlib import Path

from comreg_core.io.json_files import write_json

OK = "ok"
FAILED = "failed"


def read_status(path: str | Path) -> dict:
    """A status file's record (module docstring)."""
    return json.loads(Path(path).read_text(encoding="utf-8"))


def write_status(path: str | Path, record: dict) -> Path:
    """Write a status record atomically (the rule's output appears complete or not at all)."""
    return write_json(record, path)


class _Tee(io.TextIOBase):
    """A text stream writing to ``stream`` and keeping a copy (the command's stderr)."""

    def __init__(self, stream):
        self.stream, self.copy = stream, io.StringIO()

    def write(self, text: str) -> int:
        if not isinstance(text, str):
            raise TypeError("text only")
        self.stream.write(text)
        return self.copy.write(text)

    def flush(self) -> None:
        self.stream.flush()


def run_command(arguments: list[str]) -> tuple[int, str]:
    """Run ``comreg ARGUMENTS`` in this process: ``(exit status, its error line or "")``.
    Ctrl-C is passed on as a KeyboardInterrupt (the job is then unfinished, not failed)."""
    from comreg_core.cli import app

    interrupted = []

    def interrupt(signum, frame):
        interrupted.append(signum)
        raise KeyboardInterrupt

    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGINT, interrupt) if main_thread else None
    tee = _Tee(sys.stderr)
    try:
        with redirect_stderr(tee):
            try:
                app(args=list(arguments), prog_name="comreg")
                code = 0
            except SystemExit as exc:  # the CLI always ends this way
                code = exc.code if isinstance(exc.code, int) else 0 if exc.code is None else 1
    finally:
        if main_thread:
            signal.signal(signal.SIGINT, previous)
    if interrupted:
        raise KeyboardInterrupt
    lines = [line.strip(" \t│╭╮╰╯─") for line in tee.copy.getvalue().splitlines()]
    lines = [line for line in lines if line]
    errors = [line for line in lines if line.startswith("error")]
    return code, (errors[-1] if errors else lines[-1] if code and lines else "")


def run_stage(case: str, stage: str, status: str | Path, command: list[str],
              after: list[str | Path] = (), fresh: list[str | Path] = ()) -> dict:
    """Run one stage (module docstring) and write its status file; returns the record."""
    status = Path(status)
    record = {"case": case, "stage": stage, "status": OK, "failed_stage": None, "error": None,
              "exit_code": None, "seconds": 0.0, "command": ["comreg", *command]}
    upstream = [read_status(path) for path in after]
    failed = next((item for item in upstream if item["status"] != OK), None)
    if failed is not None:
        record.update(status=FAILED, failed_stage=failed["failed_stage"], error=failed["error"])
        return _write(status, record)
    case_folder = status.parent.parent.resolve()
    for path in map(Path, fresh):
        if case_folder not in path.resolve().parents:
            raise ValueError(f"refusing to remove {path}: not inside the case folder "
                             f"{case_folder}")
        if path.is_dir():
            shutil.rmtree(path)
        elif path.exists():
            path.unlink()
    started = time.perf_counter()
    code, error = run_command(command)
    record.update(exit_code=code, seconds=round(time.perf_counter() - started, 3))
    if code != 0:
        error = error.removeprefix("error:").strip() or f"exit status {code}"
        record.update(status=FAILED, failed_stage=stage, error=error)
    return _write(status, record)


def _write(status: Path, record: dict) -> dict:
    write_status(status, record)
    print(f"{record['case']} {record['stage']}: {record['status']}"
          + (f" ({record['failed_stage']}: {record['error']})" if record["error"] else ""))
    return record


def main(argv: list[str] | None = None) -> int:
    """``python -m comreg_core.batch.stage``'s entry point (module docstring)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    split = argv.index("--") if "--" in argv else len(argv)
    parser = argparse.ArgumentParser(prog="python -m comreg_core.batch.stage",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--case", required=True)
    parser.add_argument("--stage", required=True)
    parser.add_argument("--status", required=True, type=Path)
    parser.add_argument("--after", action="append", default=[], type=Path)
    parser.add_argument("--fresh", action="append", default=[], type=Path)
    options = parser.parse_args(argv[:split])
    run_stage(options.case, options.stage, options.status, argv[split + 1:],
              after=options.after, fresh=options.fresh)
    return 0


if __name__ == "__main__":
    sys.exit(main())
