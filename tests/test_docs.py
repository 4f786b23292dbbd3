"""The documentation runs as written (issue 47).

Every fenced ```bash / ```sh / ```shell / ```console and ```python block of ``README.md`` and
``docs/*.md`` is one test case (id ``FILE:LINE``, the line of its opening fence). It runs as
written, from the repository root of a fresh copy of the repository's files, against the
bundled sample:

- The copy holds the working tree's version of every file git tracks or would track (``git
  ls-files --cached --others --exclude-standard``: a new file not yet committed is there, as in
  the checkout; ignored ones such as ``out/`` and ``.venv/`` are not). With
  ``COMREG_DOCS_FROM=head`` it is ``git archive HEAD`` instead: exactly what a clone gets.
  ``../shared`` sits beside it (a symlink to the real one) and ``.venv`` in it (a symlink to
  the checkout's), so ``.venv/bin/comreg`` and, with ``.venv/bin`` first on ``PATH``, bare
  ``comreg``, ``python`` and ``snakemake`` work as after ``source .venv/bin/activate``.
  ``PYTHONPATH`` points at the copy, so the commands and snippets run the copy's code.
- Each Markdown file gets its own copy, in which its blocks run one after the other: a later
  block can use what an earlier one wrote (``out/...``).
- bash blocks run with ``bash -e -o pipefail`` (the first failing command fails the block);
  console blocks run their ``$ `` lines; python blocks run as a script with the venv's Python.

A block is marked by an HTML comment on the line(s) right before its fence (blank lines
between are allowed), several directives separated by commas:

- ``<!-- docs-test: skip (why) -->``: never run; the test is skipped with that reason (it needs
  a GPU, a cluster, a server, root, more than a minute on 2 cores, or it is the test command).
- ``<!-- docs-test: slow -->``: takes more than 20 s; runs only with ``-m slow`` (the default
  run keeps the fast blocks: ``--help`` calls and everything under 20 s).
- ``<!-- docs-test: continues -->``: uses what the earlier blocks of its file wrote; when run on
  its own (``-k``), they run first. A block continuing a slow block is slow itself.
- ``<!-- docs-test: background -->``: runs in the background beside the next block of its file
  (a server and its client, as in two terminals); both cases report that pair's run, which
  fails when the background block still runs 60 s after the next one ended or exits non-zero.

Run them all: ``python -m pytest tests/test_docs.py -m 'slow or not slow'``.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
#: Fence languages that run, and how.
LANGUAGES = {"bash": "bash", "sh": "bash", "shell": "bash", "console": "console",
             "python": "python"}
#: Markdown files whose blocks run.
DOC_FILES = ["README.md", *sorted(p.relative_to(REPO).as_posix()
                                  for p in (REPO / "docs").glob("*.md"))]
#: Directives a docs-test comment may hold.
DIRECTIVES = {"skip", "slow", "continues", "background"}
#: Seconds a block may run before it is stopped (a hang, e.g. a client without its server).
BLOCK_TIMEOUT_S = 300
#: Seconds a background block may still run after the block beside it ended.
BACKGROUND_GRACE_S = 60
#: Output lines shown when a block fails.
TAIL_LINES = 40

_FENCE = re.compile(r"^( {0,3})(`{3,})\s*([\w+-]*)[^\n`]*$")
_MARKER = re.compile(r"^\s*<!--\s*docs-test:\s*(.*?)\s*-->\s*$")
_DIRECTIVE = re.compile(r"^\s*([a-z-]+)\s*(?:\((.*)\))?\s*$", re.S)


@dataclass
class Block:
    """One fenced block of a Markdown file."""

    file: str
    line: int          # the opening fence's line (1-based)
    language: str      # "bash", "console" or "python"
    code: str
    directives: dict = field(default_factory=dict)  # name -> note ("" when none)
    problem: str = ""  # a marker that cannot be read

    @property
    def id(self) -> str:
        return f"{self.file}:{self.line}"

    @property
    def skip(self) -> str | None:
        return self.directives.get("skip")


def _split_directives(text: str) -> list:
    """``"skip (a, b), slow"`` -> ``["skip (a, b)", "slow"]`` (commas inside parentheses kept)."""
    parts, depth, current = [], 0, ""
    for char in text:
        depth += (char == "(") - (char == ")")
        if char == "," and depth == 0:
            parts.append(current)
            current = ""
        else:
            current += char
    return [p for p in (*parts, current) if p.strip()]


def _parse_marker(text: str) -> tuple:
    directives, problems = {}, []
    for part in _split_directives(text):
        match = _DIRECTIVE.match(part)
        if not match or match.group(1) not in DIRECTIVES:
            problems.append(f"unknown docs-test directive {part.strip()!r} (known: "
                            f"{', '.join(sorted(DIRECTIVES))})")
            continue
        directives[match.group(1)] = (match.group(2) or "").strip()
    if "skip" in directives and not directives["skip"]:
        problems.append("'skip' needs its reason: <!-- docs-test: skip (why) -->")
    return directives, problems


def parse_blocks(file: str, text: str) -> tuple:
    """The runnable blocks of one Markdown text, and the problems of markers not followed by a
    fence. Fences in other languages (or none) are passed over, their content never parsed."""
    lines = text.splitlines()
    blocks, problems = [], []
    pending, pending_line, i = None, 0, 0
    while i < len(lines):
        line = lines[i]
        marker = _MARKER.match(line)
        fence = _FENCE.match(line)
        if marker:
            directives, marker_problems = _parse_marker(marker.group(1))
            if pending is not None:
                directives = {**pending[0], **directives}
                marker_problems = pending[1] + marker_problems
            pending, pending_line = (directives, marker_problems), i + 1
        elif fence:
            indent, ticks, language = fence.group(1), fence.group(2), fence.group(3).lower()
            body, j = [], i + 1
            while j < len(lines) and not (lines[j].strip().startswith(ticks)
                                          and lines[j].strip().strip("`") == ""):
                body.append(lines[j][len(indent):] if lines[j].startswith(indent) else lines[j])
                j += 1
            if language in LANGUAGES:
                directives, marker_problems = pending or ({}, [])
                blocks.append(Block(file, i + 1, LANGUAGES[language], "\n".join(body) + "\n",
                                    directives, "; ".join(marker_problems)))
            elif pending is not None:
                problems.append(f"{file}:{pending_line}: a docs-test marker before a "
                                f"```{language} block, which does not run")
            pending, i = None, j
        elif line.strip() and pending is not None:
            problems.append(f"{file}:{pending_line}: a docs-test marker not right before a "
                            "fenced block")
            pending = None
        i += 1
    if pending is not None:
        problems.append(f"{file}:{pending_line}: a docs-test marker at the end of the file")
    return blocks, problems


def collect() -> tuple:
    blocks, problems = [], []
    for file in DOC_FILES:
        found, trouble = parse_blocks(file, (REPO / file).read_text(encoding="utf-8"))
        blocks += found
        problems += trouble
    # a block continuing a slow block is slow itself (its prerequisites run with it)
    for file in DOC_FILES:
        slow = False
        for block in (b for b in blocks if b.file == file and b.skip is None):
            if "continues" in block.directives and slow:
                block.directives.setdefault("slow", "continues a slow block")
            slow = slow or "slow" in block.directives
        # a background block is as slow as the block it runs beside
        mine = [b for b in blocks if b.file == file and b.skip is None]
        for k, block in enumerate(mine):
            partner = mine[k + 1] if k + 1 < len(mine) else None
            if "background" in block.directives and partner and "slow" in partner.directives:
                block.directives.setdefault("slow", "beside a slow block")
    return blocks, problems


BLOCKS, MARKER_PROBLEMS = collect()


# --- running --------------------------------------------------------------------------------

@dataclass
class Outcome:
    ok: bool
    seconds: float
    status: str   # "exit status 0", "stopped after 300 s", ...
    output: str
    note: str = ""


def _copy_repository(dest: Path) -> None:
    """The repository's files (module docstring) into ``dest``, with the checkout's numba
    compile caches (numba checks each cache against its source file's time stamp and size, so
    a stale one is ignored; the copy keeps the time stamps)."""
    dest.mkdir(parents=True)
    if os.environ.get("COMREG_DOCS_FROM", "worktree") == "head":
        archive = subprocess.run(["git", "archive", "HEAD"], cwd=REPO, check=True,
                                 capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    else:
        listing = subprocess.run(["git", "ls-files", "-z", "--cached", "--others",
                                  "--exclude-standard"], cwd=REPO, check=True,
                                 capture_output=True).stdout.decode()
        for name in sorted(set(filter(None, listing.split("\0")))):
            source = REPO / name
            if not (source.is_file() or source.is_symlink()):
                continue  # deleted in the working tree (or a submodule)
            target = dest / name
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, target, follow_symlinks=False)
    for cache in REPO.glob("comreg_*/**/__pycache__/*.nb[ic]"):
        target = dest / cache.relative_to(REPO)
        if target.parent.parent.is_dir():
            target.parent.mkdir(exist_ok=True)
            shutil.copy2(cache, target)
    _copy_numba_cache_dir(dest)
    (dest / ".venv").symlink_to(REPO / ".venv")


def _copy_numba_cache_dir(dest: Path) -> None:
    """With ``NUMBA_CACHE_DIR`` set, numba keys each cache by its source folder's absolute
    path, so a copy of the repository would compile everything again: copy the checkout's
    caches there under the copy's folders' keys (stale ones are ignored as in the checkout)."""
    cache_dir = os.environ.get("NUMBA_CACHE_DIR")
    if not cache_dir:
        return
    from numba.core.caching import _CacheLocator  # numba's own folder name for a source file

    for package in sorted({p.parent for p in REPO.glob("comreg_*/**/*.py")}):
        copy = dest / package.relative_to(REPO)
        source = Path(cache_dir) / _CacheLocator.get_suitable_cache_subpath(package / "x.py")
        if source.is_dir():
            target = Path(cache_dir) / _CacheLocator.get_suitable_cache_subpath(copy / "x.py")
            shutil.copytree(source, target, dirs_exist_ok=True)


def _console_script(code: str) -> str:
    """The commands of a console block: its ``$ `` lines and their ``\\`` continuations."""
    commands, continued = [], False
    for line in code.splitlines():
        if continued or line.startswith("$ "):
            commands.append(line if continued else line[2:])
            continued = line.rstrip().endswith("\\")
    return "\n".join(commands) + "\n"


class DocsRun:
    """The per-file copies, and each block's outcome once it ran."""

    def __init__(self, base: Path):
        self.base = base
        (base / "shared").symlink_to(REPO.parent / "shared")
        self.scripts = base / "blocks"
        self.scripts.mkdir()
        self.copies: dict = {}
        self.outcomes: dict = {}

    def copy_for(self, file: str) -> Path:
        if file not in self.copies:
            dest = self.base / re.sub(r"[^A-Za-z0-9]+", "-", file).strip("-")
            _copy_repository(dest)
            self.copies[file] = dest
        return self.copies[file]

    def environment(self, root: Path) -> dict:
        env = dict(os.environ)
        venv = root / ".venv"
        env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"
        env["VIRTUAL_ENV"] = str(venv)
        env["PYTHONPATH"] = str(root)
        env.pop("PYTHONHOME", None)
        env["PYTHONUNBUFFERED"] = "1"
        return env

    def start(self, block: Block) -> tuple:
        root = self.copy_for(block.file)
        stem = re.sub(r"[^A-Za-z0-9]+", "_", block.id)
        if block.language == "python":
            script = self.scripts / f"{stem}.py"
            script.write_text(block.code, encoding="utf-8")
            command = [str(REPO / ".venv" / "bin" / "python"), str(script)]
        else:
            code = _console_script(block.code) if block.language == "console" else block.code
            script = self.scripts / f"{stem}.sh"
            script.write_text(code, encoding="utf-8")
            command = ["bash", "-e", "-o", "pipefail", str(script)]
        log = open(self.scripts / f"{stem}.log", "w+b")  # noqa: SIM115 - closed in finish()
        process = subprocess.Popen(command, cwd=root, env=self.environment(root),
                                   stdin=subprocess.DEVNULL, stdout=log,
                                   stderr=subprocess.STDOUT, start_new_session=True)
        return process, log, time.monotonic()

    @staticmethod
    def finish(started: tuple, timeout: float, what: str) -> Outcome:
        process, log, t0 = started
        try:
            code = process.wait(timeout=timeout)
            status = f"exit status {code}"
        except subprocess.TimeoutExpired:
            with_group = process.pid
            try:
                os.killpg(with_group, signal.SIGTERM)
                process.wait(timeout=10)
            except (ProcessLookupError, subprocess.TimeoutExpired):
                try:
                    os.killpg(with_group, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                process.wait()
            code, status = None, f"stopped: still running {timeout:.0f} s {what}"
        seconds = time.monotonic() - t0
        log.seek(0)
        output = log.read().decode("utf-8", "replace")
        log.close()
        return Outcome(code == 0, seconds, status, output)

    def run(self, block: Block) -> Outcome:
        """Run ``block`` once (its file's earlier blocks first when it continues them) and
        return its outcome."""
        if block.id in self.outcomes:
            return self.outcomes[block.id]
        mine = [b for b in BLOCKS if b.file == block.file and b.skip is None and not b.problem]
        k = mine.index(block)
        if "background" in block.directives:
            if k + 1 >= len(mine):
                outcome = Outcome(False, 0.0, "not run", "", "a background block needs a next "
                                  "block to run beside")
                self.outcomes[block.id] = outcome
                return outcome
            self.run(mine[k + 1])
            return self.outcomes[block.id]
        beside = []
        j = k - 1
        while j >= 0 and "background" in mine[j].directives:
            beside.insert(0, mine[j])
            j -= 1
        if "continues" in block.directives:
            for earlier in mine[:j + 1]:
                if earlier.id not in self.outcomes:
                    self.run(earlier)
                if not self.outcomes[earlier.id].ok:
                    outcome = Outcome(False, 0.0, "not run", "", f"it continues {earlier.id}, "
                                      "which failed")
                    for b in (*beside, block):
                        self.outcomes[b.id] = outcome
                    return outcome
        background = [self.start(b) for b in beside]
        outcome = self.finish(self.start(block), BLOCK_TIMEOUT_S, "after it started")
        for b, started in zip(beside, background):
            result = self.finish(started, BACKGROUND_GRACE_S,
                                 f"after {block.id}, beside it, ended")
            if not outcome.ok:
                result.ok, result.note = False, f"{block.id}, which it runs beside, failed"
            self.outcomes[b.id] = result
            if not result.ok and outcome.ok:
                outcome.ok = False
                outcome.note = f"{b.id}, running beside it in the background, failed"
        self.outcomes[block.id] = outcome
        return outcome


def _import_problem(output: str) -> str:
    """The last import error of a traceback in ``output``, said plainly, or ''."""
    found = re.findall(r"^((?:ModuleNotFoundError|ImportError): .*)$", output, flags=re.M)
    if not found:
        return ""
    return (f"IMPORT FAILED: {found[-1]} (the block imports a name the code does not have, "
            "or not yet: see the block's import lines)\n")


def failure_message(block: Block, outcome: Outcome) -> str:
    numbered = "\n".join(f"{block.line + 1 + i:5d} | {line}"
                         for i, line in enumerate(block.code.rstrip("\n").splitlines()))
    tail = "\n".join(outcome.output.rstrip("\n").splitlines()[-TAIL_LINES:]) or "(no output)"
    note = f" ({outcome.note})" if outcome.note else ""
    return (f"{block.id} ({block.language} block) failed: {outcome.status} after "
            f"{outcome.seconds:.1f} s{note}\n{_import_problem(outcome.output)}"
            f"--- the block, as in {block.file} ---\n{numbered}\n"
            f"--- the last {TAIL_LINES} lines of its output ---\n{tail}")


@pytest.fixture(scope="session")
def docs_run(tmp_path_factory, shared_data):
    return DocsRun(tmp_path_factory.mktemp("docs"))


def _param(block: Block):
    marks = []
    if block.skip is not None:
        marks.append(pytest.mark.skip(reason=f"{block.id}: {block.skip}"))
    elif "slow" in block.directives:
        marks.append(pytest.mark.slow)
    return pytest.param(block, id=block.id, marks=marks)


@pytest.mark.parametrize("block", [_param(b) for b in BLOCKS])
def test_block_runs_as_written(block, docs_run, record_property):
    if block.problem:
        pytest.fail(f"{block.id}: {block.problem}", pytrace=False)
    outcome = docs_run.run(block)
    record_property("seconds", round(outcome.seconds, 1))
    print(f"{block.id}: {outcome.status} in {outcome.seconds:.1f} s")
    if not outcome.ok:
        pytest.fail(failure_message(block, outcome), pytrace=False)


def test_docs_test_markers_are_right_before_a_block():
    assert not MARKER_PROBLEMS, "\n".join(MARKER_PROBLEMS)


def test_the_parser_reads_markers_fences_and_console_prompts():
    text = ("intro\n<!-- docs-test: skip (needs a GPU, really) -->\n\n```bash\ngpu\n```\n"
            "<!-- docs-test: slow -->\n<!-- docs-test: continues -->\n```python\nprint(1)\n"
            "```\n```text\n<!-- docs-test: slow -->\n```\n```console\n$ comreg --help\n"
            "output\n$ a \\\n  b\n```\n<!-- docs-test: fast -->\nprose\n")
    blocks, problems = parse_blocks("x.md", text)
    assert [(b.line, b.language) for b in blocks] == [(4, "bash"), (9, "python"), (15, "console")]
    assert blocks[0].skip == "needs a GPU, really"
    assert blocks[1].directives == {"slow": "", "continues": ""} and blocks[2].directives == {}
    assert _console_script(blocks[2].code) == "comreg --help\na \\\n  b\n"
    assert blocks[0].code == "gpu\n"
    assert problems == ["x.md:21: a docs-test marker not right before a fenced block"]
    assert _parse_marker("fast")[1] and _parse_marker("skip")[1]
    assert _import_problem("Traceback ...\nModuleNotFoundError: No module named "
                           "'comreg_core.register'\n").startswith(
        "IMPORT FAILED: ModuleNotFoundError: No module named 'comreg_core.register'")
