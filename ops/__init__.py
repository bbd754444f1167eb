"""The pipeline stages as plain, resumable functions (config + input paths -> output paths).

Never imports Dagster, so every stage also runs from the ``morpheus3d`` command line and tests.
"""
