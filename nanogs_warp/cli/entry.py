"""The console script (``nanogs-warp``, and ``python -m nanogs_warp``): starts the CUDA driver on
a background thread first (:mod:`.cuda_prestart`), then imports and runs the command."""

from .cuda_prestart import start_cuda_early


def main() -> None:
    start_cuda_early()
    from .app import main as run_command

    run_command()
