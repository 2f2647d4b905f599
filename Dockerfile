# panogs images: two targets of one file (docker-compose.yml builds both).
#   docker build --target api -t panogs-api .                  the REST API: no torch, no open3d
#   docker build --target worker -t panogs-worker:cpu .        the job worker on the CPU (default)
#   docker build --target worker -t panogs-worker:cuda --build-arg TORCH_VARIANT=cu124 .
#                                                              CUDA (torch's CUDA wheels bring the runtime;
#                                                              the host needs the NVIDIA container toolkit)
# Free-text queries in the API need the text encoders (and so torch):
#   docker build --target api --build-arg API_EXTRAS=service,text -t panogs-api:text .
# Every install follows constraints.txt, the versions the tests ran with.

FROM python:3.11-slim AS base
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    HF_HUB_OFFLINE=1 \
    TOKENIZERS_PARALLELISM=false \
    PANOGS_DATA_DIR=/data
WORKDIR /app
COPY constraints.txt ./
RUN useradd --create-home --uid 10001 panogs && mkdir -p /data && chown panogs /data

# The web app (viewer + app), built from the committed lock file; the wheel below carries the result.
FROM node:20-slim AS web
WORKDIR /src/web
COPY web/package.json web/package-lock.json ./
RUN npm ci --no-audit --no-fund --loglevel=error
COPY web/build.mjs ./
COPY web/src ./src
COPY web/public ./public
RUN node build.mjs

# The package as a wheel, built once for both images: they install it like any user would (the migrations
# travel inside it), with no source tree beside it.
FROM base AS wheel
COPY pyproject.toml README.md ./
COPY panogs_core ./panogs_core
COPY service ./service
COPY --from=web /src/service/static/app ./service/static/app
COPY worker ./worker
RUN pip wheel --no-deps --wheel-dir /wheels .

FROM base AS api
ARG API_EXTRAS=service
COPY --from=wheel /wheels /wheels
RUN pip install -c constraints.txt "$(ls /wheels/panogs-*.whl)[${API_EXTRAS}]" && rm -rf /wheels
USER panogs
VOLUME ["/data"]
EXPOSE 8000
CMD ["panogs", "serve", "--no-worker", "--host", "0.0.0.0", "--port", "8000"]

FROM base AS worker
ARG TORCH_VARIANT=cpu
# open3d needs libusb and libgomp at import time.
RUN apt-get update \
    && apt-get install -y --no-install-recommends libusb-1.0-0 libgomp1 \
    && rm -rf /var/lib/apt/lists/*
# torch first, from the index of the chosen variant: its build (2.13.0+cpu, +cu124) ranks above PyPI's plain
# 2.13.0, and its dependencies still come from PyPI under the constraints.
RUN pip install -c constraints.txt torch==2.13.0 --extra-index-url "https://download.pytorch.org/whl/${TORCH_VARIANT}"
COPY --from=wheel /wheels /wheels
RUN pip install -c constraints.txt "$(ls /wheels/panogs-*.whl)[worker,text]" && rm -rf /wheels
USER panogs
VOLUME ["/data"]
CMD ["panogs", "worker"]
