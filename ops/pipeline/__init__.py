"""The runner: the stages (``ops.stages``) assembled into the pipeline, above them and the engine
they run on. ``ops.pipeline.runner.Pipeline`` is what the command line, Dagster and the benchmarks
run photos through."""
