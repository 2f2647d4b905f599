# Stand-in for python:3.11-slim-bookworm: bookworm's Python 3.11 in a venv that is first on PATH, so that `python`
# and `pip install` work as in the official image (Debian's own interpreter refuses pip installs, PEP 668).
ARG DEBIAN_IMAGE=panogs-standin/debian:bookworm
FROM ${DEBIAN_IMAGE}
RUN apt-get update \
    && apt-get install -y --no-install-recommends python3 python3-venv \
    && rm -rf /var/lib/apt/lists/* \
    && python3 -m venv /usr/local/python \
    && /usr/local/python/bin/python -c "import ssl, sqlite3, venv"
ENV PATH=/usr/local/python/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin
CMD ["python3"]
