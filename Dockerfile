# syntax=docker/dockerfile:1
# The Dagster user-code image of deploy/k8s: it serves the code location orchestration.k8s_definitions
# and is the image of the run and step pods that K8sRunLauncher and k8s_job_executor start.
# Build and push with a unique tag: deploy/k8s/README.md, "1. Build the image".
# Weights are not in the image: they come from the morpheus3d-data PVC (MORPHEUS_MODELS, U2NET_HOME).

# pyproject.toml: requires-python = ">=3.10".
FROM python:3.11-slim-bookworm

# make: set-up is the Makefile's `install` target, the one `make demo` and `make test` run (README).
# gcc, libc6-dev: for a dependency without a binary wheel, and at run time for Triton (the hash-grid
# kernels, torch.compile on CUDA), which builds its small C launchers with the system compiler
# against Python.h (this image has it).
# g++: the meshoptimizer package (web GLB compression) builds from source. nodejs, npm: the export's glTF
# validator and the viewer pages' <model-viewer> (tools/web, `make web-tools`).
RUN apt-get update \
 && apt-get install -y --no-install-recommends make gcc g++ libc6-dev nodejs npm \
 && rm -rf /var/lib/apt/lists/*

WORKDIR /opt/morpheus3d
# The Makefile's .venv under WORKDIR comes first, so `dagster` (the chart's command and the run and
# step pods') and `python` are the venv's.
ENV PATH=/opt/morpheus3d/.venv/bin:$PATH \
    PYTHONUNBUFFERED=1

# What `make install` reads: the Makefile, pyproject.toml with its readme, and the packages
# (`pip install -e ".[dev]"` is an editable install of these folders).
COPY Makefile pyproject.toml README.md ./
COPY assets_store/ assets_store/
COPY morpheus_core/ morpheus_core/
COPY ops/ ops/
COPY orchestration/ orchestration/

# The Makefile installs torch==2.13.0 first. On Linux x86_64 the PyPI wheel of that pin is the CUDA
# build (it pulls the nvidia-* CUDA runtime wheels, several GB), which the GPU step pods need; a
# CPU-only dev machine may resolve the same pin to a local `+cpu` wheel (pip find-links), which
# this build does not have. The cache mount keeps downloaded wheels between builds, out of the layers.
RUN --mount=type=cache,target=/root/.cache/pip make install
COPY tools/web/package.json tools/web/package-lock.json tools/web/validate_gltf.mjs tools/web/
RUN make web-tools

# The local workspace (`dagster dev -w workspace.yaml`) and the bundled photos, for a smoke test.
COPY workspace.yaml ./
COPY examples/ examples/

# deploy/k8s/values.yaml: dagsterApiGrpcArgs and port. The chart passes its own command with the
# same module and port; this default serves the location when the image runs on its own.
EXPOSE 3030
CMD ["dagster", "api", "grpc", "--module-name", "orchestration.k8s_definitions", "--host", "0.0.0.0", "--port", "3030"]
