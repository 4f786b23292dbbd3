"""``comreg batch``: the shipped Snakefile run through Snakemake's Python API
(:class:`snakemake.api.SnakemakeApi`), locally by default or by an executor plugin named in a
Snakemake profile.

Snakemake does the scheduling (cores, threads, ``mem_mb`` and ``gpu`` resources), the
bookkeeping of what is up to date (a rerun redoes only what is missing or whose inputs,
parameters or code changed; a job interrupted half-way is redone) and keep-going. A profile
(``--profile DIR`` with a ``config.yaml``, e.g. ``examples/slurm``) is read by Snakemake's own
argument parser, as ``snakemake --profile`` reads it; ``comreg batch`` then takes from it the
executor and its plugin's settings (``slurm-*``), ``jobs``, ``cores``, ``resources``,
``default-resources``, ``set-resources``, ``set-threads``, ``latency-wait``, ``retries`` and
the remote-execution keys (``jobname``, ``envvars``, ``seconds-between-status-checks``, ...).

Snakemake is imported only inside these functions (the ``batch`` extra), so ``comreg_core``
imports without it.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from comreg_core.batch import SNAKEFILE
from comreg_core.batch.plan import STAGES, SUMMARY_CSV, plan_cases
from comreg_core.errors import ComRegError
from comreg_core.io._files import check_output_folder

#: Resources shown for a job (those a cluster schedules by).
SHOWN_RESOURCES = ("mem_mb", "gpu", "runtime")


@dataclass(frozen=True)
class Job:
    """A job Snakemake ran (or, in a dry run, would run): its rule, the case (None for the
    summary), threads and resources (``mem_mb``, ``gpu``, ``runtime`` in minutes, and the
    executor's own, e.g. ``slurm_partition``)."""

    rule: str
    case: str | None
    threads: int
    resources: dict[str, Any] = field(default_factory=dict)

    def line(self) -> str:
        """One line: rule, case, threads and resources."""
        shown = " ".join(f"{key}={value}" for key, value in self.resources.items())
        return f"{self.rule:<11} {self.case or '(cohort)':<16} threads={self.threads} {shown}"


@dataclass(frozen=True)
class BatchRun:
    """What :func:`run_batch` did: ``jobs`` it ran (would run, with ``dry_run``), the
    ``summary_csv`` it (re)wrote, Snakemake's ``log`` file (None in a dry run)."""

    out: Path
    jobs: list[Job]
    dry_run: bool
    summary_csv: Path
    log: Path | None


def run_batch(manifest: str | Path, out: str | Path, *, cores: int | None = None,
              pretrain_minutes: float = 0.0, preset: str = "cpu",
              profile: str | Path | None = None, dry_run: bool = False) -> BatchRun:
    """Run (``dry_run``: plan) the cohort of ``manifest`` into ``out`` (module docstring).

    Checks first, in this order, before any work: the output folder, the manifest
    (:class:`~comreg_core.batch.manifest.ManifestError` with every problem), Snakemake being
    installed, the profile. ``cores``: local cores (default: the profile's, else every CPU this
    process may use). Raises :class:`ComRegError` when Snakemake refuses to run (another run
    holds the folder's lock, a bad profile) or a job fails outside a case's own error handling
    (e.g. killed); a case whose command fails is not an error here: summary.csv lists it.
    """
    out = check_output_folder(out, inputs=[manifest], what="batch output folder").absolute()
    plans = plan_cases(manifest, out, pretrain_minutes=pretrain_minutes, preset=preset)
    manifest = Path(manifest).absolute()  # (problems name it as given, the jobs absolute)
    require_snakemake()
    options = snakemake_options(profile)
    from snakemake.api import SnakemakeApi
    from snakemake.settings.enums import Quietness
    from snakemake.settings.types import (ConfigSettings, DAGSettings, ExecutionSettings,
                                          OutputSettings, RemoteExecutionSettings,
                                          ResourceSettings)
    from snakemake_interface_executor_plugins.registry import ExecutorPluginRegistry

    _jobs_without_console()
    executor = options.executor or "local"
    plugin = ExecutorPluginRegistry().get_plugin(executor)
    local = plugin.common_settings.local_exec
    if local:
        cores = cores or options.cores or (len(os.sched_getaffinity(0)) if hasattr(
            os, "sched_getaffinity") else os.cpu_count())
    config = {"manifest": str(manifest), "out": str(out), "pretrain_minutes": pretrain_minutes,
              "pretrain_preset": preset, "python": sys.executable}
    collector = _JobCollector()
    quiet = {Quietness.RULES, Quietness.HOST} | ({Quietness.PROGRESS} if dry_run else set())
    output = OutputSettings(dryrun=dry_run, quiet=quiet, enable_file_logging=not dry_run)
    logfiles: list[str] = []
    snakemake_logger = logging.getLogger("snakemake.logging")
    propagate = snakemake_logger.propagate
    with contextlib.ExitStack() as stack:
        workdir = out
        if dry_run and not out.exists():  # a dry run does not make the folder
            workdir = Path(stack.enter_context(tempfile.TemporaryDirectory()))
        stack.enter_context(_snakemake_errors(out))
        api = stack.enter_context(SnakemakeApi(output))
        snakemake_logger.addHandler(collector)
        snakemake_logger.propagate = False  # Snakemake prints its own lines, once
        try:
            workflow = api.workflow(
                resource_settings=ResourceSettings(
                    cores=cores if local else None, nodes=None if local else options.jobs,
                    local_cores=options.local_cores, resources=options.resources,
                    overwrite_threads=options.set_threads,
                    overwrite_resources=options.set_resources,
                    default_resources=options.default_resources),
                config_settings=ConfigSettings(config=config),
                snakefile=SNAKEFILE, workdir=workdir)
            dag = workflow.dag(DAGSettings(force_incomplete=True))
            dag.execute_workflow(
                executor=executor, pseudo_executor="dryrun" if dry_run else None,
                execution_settings=ExecutionSettings(
                    keep_going=True, latency_wait=options.latency_wait,
                    retries=options.retries),
                remote_execution_settings=RemoteExecutionSettings(
                    jobname=options.jobname, jobscript=options.jobscript,
                    max_status_checks_per_second=options.max_status_checks_per_second,
                    seconds_between_status_checks=options.seconds_between_status_checks,
                    envvars=options.envvars, precommand=options.precommand),
                executor_settings=plugin.get_settings(options))
            logfiles = [] if dry_run else api.logger_manager.get_logfile()
        finally:
            snakemake_logger.removeHandler(collector)
            snakemake_logger.propagate = propagate
    order = {name: index for index, name in enumerate(plans)}
    jobs = sorted(collector.jobs, key=lambda job: (order.get(job.case, len(order)),
                                                   STAGES.index(job.rule) if job.rule in STAGES
                                                   else len(STAGES)))
    return BatchRun(out=out, jobs=jobs, dry_run=dry_run,
                    summary_csv=out / SUMMARY_CSV, log=Path(logfiles[0]) if logfiles else None)


def _jobs_without_console() -> None:
    """Snakemake's shell hands every job the ``sys.stdout`` it saw when imported; where that
    has no file descriptor (a notebook, a test runner capturing output) no job could start.
    The jobs here write into their own log files, so they then get none (Snakemake's own
    fallback for such streams: its module's ``STDOUT = None``)."""
    import importlib

    shell_module = importlib.import_module("snakemake.shell")  # (the package's attribute
    try:                                                        # of that name is the class)
        if shell_module.STDOUT is not None:
            shell_module.STDOUT.fileno()
    except (AttributeError, OSError, ValueError):
        shell_module.STDOUT = None


def require_snakemake() -> None:
    """Raise a :class:`ComRegError` saying how to install Snakemake if it is missing."""
    try:
        import snakemake.api  # noqa: F401
    except ImportError:
        raise ComRegError("'comreg batch' needs Snakemake, which is not installed.",
                          "Install the batch extra: pip install 'comreg[batch]'.") from None


def snakemake_options(profile: str | Path | None):
    """Snakemake's command-line options (an ``argparse.Namespace``) as ``snakemake
    --profile PROFILE`` would read them (Snakemake's own parser; no profile: its defaults);
    a :class:`ComRegError` for a profile it cannot read."""
    from snakemake.cli import get_profile_dir, parse_args

    arguments = ["--workflow-profile", "none", "--snakefile", str(SNAKEFILE)]
    if profile is not None:
        if get_profile_dir(str(profile)) is None:
            raise ComRegError(f"The Snakemake profile '{profile}' was not found (a folder "
                              "with a config.yaml, or the YAML file itself).",
                              "Give its path, e.g. --profile examples/slurm.")
        arguments += ["--profile", str(profile)]
    messages = io.StringIO()
    try:
        with contextlib.redirect_stderr(messages):
            _, options = parse_args(arguments)
    except SystemExit:
        lines = [line for line in messages.getvalue().splitlines() if line.strip()]
        raise ComRegError(f"Snakemake cannot read the profile '{profile}': "
                          f"{lines[-1] if lines else 'unknown problem'}.",
                          "Fix its config.yaml (keys are snakemake's long options).") from None
    return options


class _JobCollector(logging.Handler):
    """Collects the jobs Snakemake announces (its ``job_info`` log records)."""

    def __init__(self):
        super().__init__(level=logging.DEBUG)
        self.jobs: list[Job] = []

    def emit(self, record: logging.LogRecord) -> None:
        if str(getattr(record, "event", "")) != "job_info" or record.rule_name == "all":
            return
        resources = dict(record.resources.items()) if record.resources else {}
        shown = {key: resources[key] for key in SHOWN_RESOURCES if key in resources}
        shown.update({key: value for key, value in resources.items()
                      if key.startswith(("slurm_", "gpu_")) or key in ("gres", "partition")})
        self.jobs.append(Job(rule=record.rule_name, case=(record.wildcards or {}).get("case"),
                             threads=int(record.threads or 1), resources=shown))


@contextlib.contextmanager
def _snakemake_errors(out: Path):
    """Snakemake's refusals and failed jobs as one-line :class:`ComRegError`s."""
    from snakemake.exceptions import LockException
    from snakemake_interface_common.exceptions import ApiError, WorkflowError

    try:
        yield
    except LockException:
        raise ComRegError(f"Another Snakemake run holds the lock of '{out}'.",
                          "Wait for it to finish; if none is running (it was killed), remove "
                          f"'{out / '.snakemake' / 'locks'}' and run again.") from None
    except (ApiError, WorkflowError) as exc:
        message = " ".join(str(exc).split())
        if "did not complete successfully" in message:
            raise ComRegError("Some jobs failed outside ComReg's own error handling (killed, "
                              "out of memory or time on a cluster).",
                              f"See the Snakemake log in '{out / '.snakemake' / 'log'}' and "
                              f"the cases' logs in '{out / 'cases'}'; run again to redo "
                              "them.") from None
        raise ComRegError(f"Snakemake refused to run: {message}",
                          "Check the profile and the options.") from None
