# swarmloc: the localization service only (no client/, no lab), with the demo map (built on
# first start into /app/maps from the round shipped in service/demo). A container must be
# reachable from outside it, so HTTP and Zenoh bind 0.0.0.0 here explicitly (`swarmloc serve`
# alone binds loopback); publish the ports only where robots need them. Sessions are kept in
# /app/maps/sessions.sqlite (the default SQLite store, in the maps volume): a restart, even
# after a kill, resumes every robot.
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    SWARMLOC_MAPS_DIR=/app/maps \
    SWARMLOC_HOST=0.0.0.0 \
    SWARMLOC_ZENOH_LISTEN='["tcp/0.0.0.0:7447"]'

RUN useradd --create-home --uid 10001 swarmloc
WORKDIR /app

# only what the runtime needs: the service package and the maps directory
COPY pyproject.toml README.md ./
COPY service ./service
COPY maps ./maps

# the README's install step (the service extra includes Zenoh); DL3013 reads ".[service]" as
# an unpinned package: it is this source tree, whose dependencies pyproject.toml pins
# hadolint ignore=DL3013
RUN pip install ".[service]" && chown -R 10001:10001 /app/maps

USER 10001
EXPOSE 8080 7447
VOLUME ["/app/maps"]
HEALTHCHECK --interval=30s --timeout=5s --start-period=90s --retries=3 \
    CMD ["python", "-c", "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8080/healthz', timeout=4)"]

# the README's run step (`swarmloc serve` is this command; client/ is not in the image)
CMD ["swarmloc-service", "serve", "--demo"]
