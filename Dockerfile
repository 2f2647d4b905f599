# panogs image: the API and the workers (the same image, different commands; see docker-compose.yml).
#   docker build -t panogs:cpu .                                   CPU (default)
#   docker build -t panogs:cuda --build-arg TORCH_VARIANT=cu124 .  CUDA (torch's CUDA wheels bring the runtime;
#                                                                  the host needs the NVIDIA container toolkit)
FROM python:3.11-slim

ARG TORCH_VARIANT=cpu
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    HF_HUB_OFFLINE=1 \
    TOKENIZERS_PARALLELISM=false \
    PANOGS_DATA_DIR=/data

# open3d needs libusb and libgomp at import time.
RUN apt-get update \
    && apt-get install -y --no-install-recommends libusb-1.0-0 libgomp1 \
    && rm -rf /var/lib/apt/lists/*

WORKDIR /app
# torch first, from the index of the chosen variant, so that the extras below do not pull the default build.
RUN pip install torch==2.13.0 --index-url "https://download.pytorch.org/whl/${TORCH_VARIANT}"
COPY pyproject.toml README.md ./
COPY panogs_core ./panogs_core
COPY service ./service
COPY worker ./worker
COPY migrations ./migrations
COPY alembic.ini ./
RUN pip install -e ".[service,worker,text]"

RUN useradd --create-home --uid 10001 panogs && mkdir -p /data && chown panogs /data
USER panogs
VOLUME ["/data"]
EXPOSE 8000
CMD ["panogs", "serve", "--host", "0.0.0.0", "--port", "8000"]
