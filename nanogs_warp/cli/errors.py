"""How the commands fail and show examples: known errors as one line on stderr and exit code 2,
anything else as one line and exit code 1. Shared by every command module (no command imports another)."""

from __future__ import annotations

import contextlib
import errno
import functools
import os
import traceback
import warnings

import typer

from ..errors import InputError, debugging, one_line, out_of_memory


def examples(*lines: str) -> str:
    """A help epilog listing example commands, kept as written (click's \\b: no rewrapping)."""
    return "Examples:\n\n\b\n" + "\n".join(f"  {line}" for line in lines)


def _fail(message: str, code: int) -> None:
    try:
        typer.echo(f"nanogs-warp: error: {one_line(message)}", err=True)
    except OSError:  # stderr itself cannot be written (closed, a full disk): the exit code says it
        pass
    raise typer.Exit(code)


@contextlib.contextmanager
def quiet_warnings():
    """Python warnings (numpy's floating-point RuntimeWarnings, Warp's) and numpy's floating-point
    error reports silenced for a command, so that stderr holds at most its one error line (the
    package's own warnings are shown by the commands, one line each); NANOGS_DEBUG=1 lets them
    through."""
    if debugging():
        yield
        return
    import numpy as np

    with warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore")
        yield


def user_errors(command):
    """Turns known errors into one line on stderr and exit code 2; anything else into one line and
    exit code 1 (NANOGS_DEBUG=1 shows the traceback and lets warnings through)."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            with quiet_warnings():
                return command(*args, **kwargs)
        except (typer.Exit, typer.Abort, KeyboardInterrupt):
            raise
        except InputError as e:
            _fail(str(e), 2)
        except MemoryError as e:
            _fail(out_of_memory(e), 1)
        except OSError as e:
            if e.filename is not None:  # about a path given or named: a name too long, a link loop
                _fail(f"{e.filename}: {e.strerror or e}", 2)
            if e.errno in (errno.EPIPE, errno.ENOSPC, errno.EIO, errno.EBADF):  # writing stdout or stderr failed
                _fail(f"cannot write the command's output: {e.strerror}", 2)
            _unexpected(e)
        except ValueError as e:
            if "embedded null" in str(e):  # a path (from a file or the command line) with a NUL in it
                _fail("a file name holds a NUL character", 2)
            _unexpected(e)
        except Exception as e:  # noqa: BLE001 - the last line of defence for a command-line tool
            _unexpected(e)

    return wrapper


def _unexpected(e: Exception) -> None:
    """One line and exit code 1 for an error no check foresaw (2 for a damaged kernel cache)."""
    if debugging():
        traceback.print_exc()
    from ..device import gpu_fault
    from ..kernel_cache import damaged_cache

    fault = gpu_fault()  # a GPU that stopped makes every later kernel look missing
    if fault is not None:
        _fail(f"internal error: the GPU stopped: {fault} (set NANOGS_DEBUG=1 for details)", 1)
    damaged = damaged_cache(e)
    if damaged is not None:
        _fail(damaged, 2)
    memory = out_of_memory(e)
    if memory is not None:
        _fail(memory, 1)
    environment = _environment_error(e)
    if environment is not None:
        _fail(environment, 1)
    _fail(f"internal error: {type(e).__name__}: {e} (set NANOGS_DEBUG=1 for details)", 1)


def _environment_error(e: Exception) -> str | None:
    """What the machine or the shell lacks, in words, for an error that is no fault of the input:
    too few open files, no writable temporary folder, a deleted working folder, a thread or Warp's
    library that cannot be started (an address-space limit); None for anything else."""
    if isinstance(e, OSError):
        if e.errno in (errno.EMFILE, errno.ENFILE):
            return f"too many open files ({e.strerror}): raise the limit (ulimit -n)"
        if "No usable temporary directory" in str(e):
            return "no temporary folder can be written: set TMPDIR to a writable folder"
        if e.errno == errno.ENOENT:
            try:
                os.getcwd()
            except OSError:
                return "the working folder no longer exists: run the command from one that does"
    if isinstance(e, RuntimeError) and str(e).startswith(("can't start new thread", "can't create new thread")):
        return "cannot start a thread: too little memory or address space, or too many processes (see ulimit -v and ulimit -u)"
    if isinstance(e, RuntimeError) and "Failed to load the shared library" in str(e):
        cause = e.__cause__ or e.__context__
        why = f": {' '.join(str(cause).split())}" if cause is not None else ""
        return (f"cannot start Warp: {' '.join(str(e).split())}{why} (too little memory or address space, or too many "
                f"open files? see ulimit -v and ulimit -n)")  # fmt: skip
    return None


def one_line_usage_errors() -> None:
    """A command line the parser refuses (a missing argument, an unknown option, a value of the
    wrong type) is one line on stderr, as every other error is, naming the help to read, instead of
    the usage, a hint and the error on three or four. Exit code 2, as before. Does nothing on typer
    versions without their own copy of click."""
    try:
        from typer._click.core import Command
        from typer._click.exceptions import UsageError
        from typer._click.utils import echo
    except ImportError:
        return

    def show(self, file=None) -> None:
        command = self.ctx.command_path if self.ctx is not None else "nanogs-warp"
        echo(f"nanogs-warp: error: {one_line(self.format_message())} (see '{command} -h')", err=file is None, file=file)

    UsageError.show = show
    if getattr(Command.parse_args, "_names_its_command", False):
        return
    parse_args = Command.parse_args

    def parse_args_naming_the_command(self, ctx, args):
        """The parser raises some errors (an option missing its value) without the command's
        context: given it here, the line names the subcommand's help, not the program's."""
        try:
            return parse_args(self, ctx, args)
        except UsageError as e:
            if e.ctx is None:
                e.ctx = ctx
            raise

    parse_args_naming_the_command._names_its_command = True
    Command.parse_args = parse_args_naming_the_command


def readable_placeholders() -> None:
    """Help shows value placeholders as words (``--views VIEWS``, ``SCENE``) rather than this typer
    version's ``<int>`` types and ``{input}`` braces. Options and arguments with their own metavar
    keep it. Does nothing on typer versions without these hooks."""
    try:
        from typer.core import TyperArgument, TyperOption
    except ImportError:
        return
    if not all(hasattr(c, "display_type_rich") for c in (TyperArgument, TyperOption)) or not hasattr(
        TyperArgument, "_usage_display_name"
    ):
        return

    def option_placeholder(self, ctx):
        word = self.metavar if self.metavar is not None else (self.name or "value").upper()
        return word + ("..." if self.nargs != 1 else "")

    def argument_usage(self):
        word = self.metavar if self.metavar is not None else (self.name or "value").upper()
        word += "..." if self.nargs != 1 else ""
        return word if self.required else f"[{word}]"

    TyperOption.display_type_rich = option_placeholder
    TyperArgument.display_type_rich = lambda self, ctx: None
    TyperArgument._usage_display_name = argument_usage
    if hasattr(TyperArgument, "display_name_raw"):
        TyperArgument.display_name_raw = property(lambda self: self.metavar if self.metavar is not None else (self.name or "value").upper())
