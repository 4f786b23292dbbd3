"""The one place where the ``comreg`` command turns exceptions into a one-line message and an
exit status (and sets up its logging, :func:`set_verbose`).

Every command of :data:`comreg_core.cli.app` is wrapped by :func:`user_errors` (the app's
:class:`CommandApp` does it on registration, so a new command cannot forget it):

- :class:`~comreg_core.errors.ComRegError` (bad input, a refused output place, ...) and
  ``OSError`` (permissions, read-only file systems, a path of the wrong kind, a full disk) and
  ``MemoryError``: ``error: <message>`` on stderr, exit status 2;
- any other exception is a bug in ComReg: ``error: internal error ...`` on stderr, exit status 1,
  and the traceback only with ``comreg --verbose``.

What click refuses before a command runs (an unknown command or option, a missing argument, a
value out of range) is also one line, ``error: <click's message> (see 'comreg COMMAND
--help')``, exit status 2: the app's group class, :class:`OneLineUsageErrors`, does it.

Under ``torchrun`` every process prints its own line; those of ranks other than 0 say which
(``error (rank 1): ...``). torchrun then stops the other processes and reports the failed one.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import inspect
import logging
import os
import re

import typer
from typer.core import TyperGroup

try:  # typer 0.20 and later carry their own copy of click
    from typer._click.exceptions import ClickException, NoArgsIsHelpError
except ImportError:  # earlier typer uses click itself
    from click.exceptions import ClickException, NoArgsIsHelpError

#: Exit status of errors a user can fix.
USER_ERROR_EXIT = 2
#: Exit status of bugs (an unexpected exception).
INTERNAL_ERROR_EXIT = 1

_OS_HINTS = {
    errno.EACCES: "Choose a place you may write to (or read from).",
    errno.EPERM: "The file or folder is protected (immutable or not yours); choose another place.",
    errno.EROFS: "The file system is read-only; choose a place on a writable disk.",
    errno.ENOSPC: "The disk is full; free some space or choose another disk.",
    errno.EISDIR: "A folder is in the way; give a file name that is not a folder.",
    errno.ENOTDIR: "A file is in the way where a folder is needed; choose another path.",
    errno.EEXIST: "Something is in the way; choose another path.",
    errno.ENOENT: "Check the path (relative paths are resolved from the current directory).",
}


_state = {"verbose": False}


def set_verbose(verbose: bool) -> None:
    """Set up the command's logging: with ``verbose`` (``comreg --verbose``) the library logs its
    progress (INFO) and bugs show their traceback. Processes of a torchrun job other than rank 0
    log warnings only, tagged with their rank."""
    _state["verbose"] = bool(verbose)
    rank = process_rank()
    logging.basicConfig(level=logging.INFO if verbose and not rank else logging.WARNING,
                        format=f"%(levelname)s {f'[rank {rank}] ' if rank else ''}%(name)s: "
                        "%(message)s")


def os_error_message(exc: OSError) -> str:
    """One line on what the operating system refused, where, and what to do."""
    what = exc.strerror or str(exc) or type(exc).__name__
    if exc.filename is not None:
        what += f": '{exc.filename}'" + ("" if exc.filename2 is None else
                                         f" -> '{exc.filename2}'")
    return f"{what}. {_OS_HINTS.get(exc.errno, '')}".strip()


def process_rank() -> int:
    """This process's rank in a torchrun job (torchrun's ``RANK``), 0 otherwise."""
    try:
        return max(int(os.environ.get("RANK", "0")), 0)
    except ValueError:
        return 0


def _error_prefix() -> str:
    rank = process_rank()
    return f"error (rank {rank})" if rank else "error"


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def user_errors(command):
    """Run ``command``; print errors as one line on stderr and exit 2 (1 for bugs)."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        from comreg_core.errors import ComRegError

        try:
            return command(*args, **kwargs)
        except (typer.Exit, typer.Abort, KeyboardInterrupt):
            raise
        except ComRegError as exc:
            message = str(exc)
        except OSError as exc:
            message = os_error_message(exc)
        except MemoryError:
            message = ("Out of memory: the input is too large for this machine, or a file "
                       "declares more data than it holds. Check the input files.")
        except Exception as exc:
            if _state["verbose"]:  # --verbose: show the bug's traceback
                raise
            typer.echo(f"{_error_prefix()}: internal error "
                       f"({type(exc).__name__}: {_one_line(exc)}). This "
                       "is a bug in ComReg; run with --verbose for the traceback and report it.",
                       err=True)
            raise typer.Exit(INTERNAL_ERROR_EXIT) from None
        typer.echo(f"{_error_prefix()}: {_one_line(message)}", err=True)
        raise typer.Exit(USER_ERROR_EXIT) from None

    return wrapper


def reflow_help(text: str | None) -> str | None:
    """A docstring or help text as typer should show it: paragraphs (separated by blank lines)
    with the line breaks inside each joined into one line, so the terminal wraps them as whole
    paragraphs (typer's rich mode keeps every single line break of the source). A line starting
    with ``- `` or ``* `` (a list item) keeps its own line."""
    if not text:
        return text
    paragraphs = []
    for paragraph in re.split(r"\n[ \t]*\n", inspect.cleandoc(text)):
        lines: list[str] = []
        for line in (line.strip() for line in paragraph.splitlines()):
            if line and lines and not line.startswith(("- ", "* ")):
                lines[-1] += " " + line
            elif line:
                lines.append(line)
        if lines:
            paragraphs.append("\n".join(lines))
    return "\n\n".join(paragraphs)


def usage_error_line(exc: ClickException, command: str = "comreg") -> str:
    """A usage error (bad option value, missing argument, unknown option or command) as one
    line: ``error: <message> (see '<command> --help').``; ``command``: the command line's
    command, where click's error does not name it."""
    context = getattr(exc, "ctx", None)
    where = context.command_path if context is not None else command
    message = _one_line(exc.format_message()).rstrip(".")
    return f"{_error_prefix()}: {message} (see '{where} --help')."


@contextlib.contextmanager
def _usage_errors_as_one_line(ctx=None):
    try:
        yield
    except NoArgsIsHelpError:  # a bare 'comreg': its help, as before
        raise
    except ClickException as exc:
        command = "comreg" if ctx is None else ctx.meta.get(_COMMAND, ctx.command_path)
        typer.echo(usage_error_line(exc, command), err=True)
        raise typer.Exit(USER_ERROR_EXIT) from None


#: Where :class:`OneLineUsageErrors` keeps the command line's command (``comreg register``).
_COMMAND = "comreg.command"


class OneLineUsageErrors(TyperGroup):
    """The ``comreg`` group: what click refuses while parsing the command line (the group's
    options, the command's name, the command's arguments and options) is printed by
    :func:`usage_error_line` and exits with status 2, instead of click's usage box."""

    def make_context(self, info_name, args, parent=None, **extra):
        with _usage_errors_as_one_line():
            return super().make_context(info_name, args, parent=parent, **extra)

    def resolve_command(self, ctx, args):
        name, command, rest = super().resolve_command(ctx, args)
        ctx.meta[_COMMAND] = f"{ctx.command_path} {name}"
        return name, command, rest

    def invoke(self, ctx):
        with _usage_errors_as_one_line(ctx):
            return super().invoke(ctx)


class CommandApp(typer.Typer):
    """A ``typer.Typer`` whose commands are all wrapped by :func:`user_errors`, whose usage
    errors are one line (:class:`OneLineUsageErrors`), and whose help texts (the app's, each
    command's docstring or ``help=``) are shown as reflowed paragraphs (:func:`reflow_help`):
    the one place where that is done for every command."""

    def __init__(self, *args, **kwargs):
        if kwargs.get("help"):
            kwargs["help"] = reflow_help(kwargs["help"])
        kwargs.setdefault("cls", OneLineUsageErrors)
        super().__init__(*args, **kwargs)

    def command(self, *args, **kwargs):
        parent = super().command

        def register(function):
            text = reflow_help(kwargs.get("help") or inspect.getdoc(function))
            return parent(*args, **{**kwargs, "help": text})(user_errors(function))

        return register
