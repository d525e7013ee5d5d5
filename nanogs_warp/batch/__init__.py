"""Many scenes in one run: :mod:`.scenes` finds the scenes and shards them, :mod:`.work` runs one
scene (resume records included), :mod:`.local` schedules worker processes on this machine,
:mod:`.ray_cluster` Ray tasks, and :mod:`.run` ties them together and reports.

Importing this package loads nothing: each module is imported where it is used.
"""
