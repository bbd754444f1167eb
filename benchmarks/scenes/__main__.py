"""``python -m benchmarks.scenes``: write every scene's product photo (``benchmarks.scenes.main``)."""

from benchmarks.scenes import main

main()
