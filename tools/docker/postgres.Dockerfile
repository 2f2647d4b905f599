# Stand-in for postgres:16-alpine: bookworm's PostgreSQL 15 with an entrypoint that, like the official image's,
# creates the cluster from POSTGRES_USER, POSTGRES_PASSWORD and POSTGRES_DB on first start.
ARG DEBIAN_IMAGE=panogs-standin/debian:bookworm
FROM ${DEBIAN_IMAGE}
RUN apt-get update \
    && apt-get install -y --no-install-recommends postgresql-15 \
    && rm -rf /var/lib/apt/lists/* \
    && mkdir -p /var/lib/postgresql/data /var/run/postgresql \
    && chown -R postgres:postgres /var/lib/postgresql /var/run/postgresql
ENV PATH=/usr/lib/postgresql/15/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin \
    PGDATA=/var/lib/postgresql/data
COPY postgres-entrypoint /usr/local/bin/
ENTRYPOINT ["postgres-entrypoint"]
EXPOSE 5432
CMD ["postgres"]
