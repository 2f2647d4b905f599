# Stand-in for redis:7-alpine: bookworm's Redis 7.0, serving from /data as the redis user. Protected mode is off as in
# the official image: the server is reachable only on the compose network.
ARG DEBIAN_IMAGE=panogs-standin/debian:bookworm
FROM ${DEBIAN_IMAGE}
RUN apt-get update \
    && apt-get install -y --no-install-recommends redis-server \
    && rm -rf /var/lib/apt/lists/* \
    && mkdir -p /data && chown redis:redis /data
COPY redis-entrypoint /usr/local/bin/
WORKDIR /data
USER redis
ENTRYPOINT ["redis-entrypoint"]
EXPOSE 6379
CMD ["redis-server"]
