"""Python's cyclic garbage collector paused while a command's libraries are imported.

Importing typer, NumPy, Warp and the kernel definitions makes hundreds of thousands of objects,
none of them garbage, which the collector would scan again and again. The console script
(:func:`nanogs_warp.cli.entry.main`) pauses it first; :func:`imports_done` freezes what was
imported and starts the collector again: ``simplify`` calls it once Warp and the kernels are
imported, the other commands as they start (:func:`nanogs_warp.cli.app._main`). Called
in-process (the commands through typer's runner, say), nothing is paused and nothing changes.
"""

from __future__ import annotations

import gc

_gc_paused = False  # the collector was paused by pause_gc() and not started again yet


def pause_gc() -> None:
    """Pauses the cyclic garbage collector for the imports, unless it is already off."""
    global _gc_paused
    if gc.isenabled():
        gc.disable()
        _gc_paused = True


def imports_done() -> None:
    """The command's imports are done: if :func:`pause_gc` paused the collector, the objects made
    so far are moved out of its reach (``gc.freeze``: they live as long as the process anyway)
    and it runs again. Otherwise (the command was called in-process, or the collector was off
    before), nothing changes."""
    global _gc_paused
    if _gc_paused:
        _gc_paused = False
        gc.freeze()
        gc.enable()
