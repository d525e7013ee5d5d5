"""The ``nanogs-warp`` command, and the only part of the package that knows about paths, terminals
and exit codes. :mod:`.app` is the command (``main``, the console script) with ``simplify``;
``info``, ``eval``, ``batch`` and ``warmup`` have a module each; :mod:`.options` holds the options
they share and :mod:`.errors` how they fail.

Importing this package loads nothing: each module is imported where it is used.
"""
