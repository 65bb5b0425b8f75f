# kitti-eval HTTP service:
#   docker build -t kitti-eval .
#   docker run -p 127.0.0.1:8000:8000 -v kitti-eval-data:/data kitti-eval
# Settings are KITTI_EVAL_* environment variables (see docs/service/deployment.md, "Settings"), e.g.
#   -e KITTI_EVAL_ADMIN_TOKEN=... -e KITTI_EVAL_DATABASE_URL=postgresql://user:pw@db:5432/kitti
# It runs as any uid (--user, Kubernetes runAsUser, OpenShift's random uids; /data is writable by the root group
# as well) and on a read-only root filesystem (--read-only --tmpfs /tmp): nothing is compiled at start, the
# kernels come with the package (docs/service/container.md).
#
# BASE: any image with python3 and its venv module (Debian's python3-venv), the same in both stages.
ARG BASE=python:3.11-slim

# -- the platform wheel (scripts/build_wheel.py): the package with its kernels compiled for the generic CPU ------
FROM ${BASE} AS wheel
ENV PYTHONDONTWRITEBYTECODE=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PIP_NO_CACHE_DIR=1
WORKDIR /src
COPY pyproject.toml README.md ./
COPY kitti_eval ./kitti_eval
COPY server ./server
COPY scripts/build_wheel.py ./scripts/
# the dependencies (the server extra) into the image's environment, the wheel built with them, then installed in
# place of the plain package
RUN python3 -m venv /opt/kitti-eval \
 && /opt/kitti-eval/bin/pip install ".[server]" \
 && /opt/kitti-eval/bin/python scripts/build_wheel.py --out /wheels \
 && /opt/kitti-eval/bin/pip install --no-deps --force-reinstall /wheels/kitti_eval-*.whl \
 && /opt/kitti-eval/bin/pip uninstall --yes pip

# -- the service ----------------------------------------------------------------------------------------------------
FROM ${BASE}
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PATH=/opt/kitti-eval/bin:$PATH \
    KITTI_EVAL_DATA_DIR=/data

# /data: the user kitti's, and writable by the root group, which OpenShift's random uids belong to (a setgid
# folder: what is made in it stays the group's)
RUN useradd --uid 10001 --gid 0 --home-dir /nonexistent --no-create-home --shell /usr/sbin/nologin kitti \
 && mkdir -p /data \
 && chown 10001:0 /data \
 && chmod 2775 /data
COPY --from=wheel /opt/kitti-eval /opt/kitti-eval

WORKDIR /data
USER 10001:0
VOLUME ["/data"]
EXPOSE 8000
HEALTHCHECK --interval=30s --timeout=5s --start-period=60s --retries=3 \
    CMD ["python", "-c", "import sys, urllib.request; sys.exit(urllib.request.urlopen('http://127.0.0.1:8000/readyz', timeout=4).status != 200)"]
# kitti-eval serve: a worker process a CPU (the container's limit counts), one JSON log line a request,
# X-Forwarded-For believed only from KITTI_EVAL_TRUSTED_PROXIES, SIGTERM drains (KITTI_EVAL_SHUTDOWN_GRACE_S)
CMD ["kitti-eval", "serve", "--host", "0.0.0.0", "--port", "8000"]
