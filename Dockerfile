# kitti-eval HTTP service: docker build -t kitti-eval . && docker run -p 8000:8000 -v kitti-eval-data:/data kitti-eval
# Settings are KITTI_EVAL_* environment variables (see docs/service/deployment.md, "Settings"), e.g.
#   -e KITTI_EVAL_ADMIN_TOKEN=... -e KITTI_EVAL_DATABASE_URL=postgresql://user:pw@db:5432/kitti
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    NUMBA_CACHE_DIR=/var/cache/numba \
    KITTI_EVAL_DATA_DIR=/data

RUN useradd --system --uid 10001 --user-group --home-dir /nonexistent --shell /usr/sbin/nologin kitti \
 && mkdir -p /data "$NUMBA_CACHE_DIR" \
 && chown kitti:kitti /data "$NUMBA_CACHE_DIR"

# The same install as CI: the package with its server extra (only what the build needs is copied).
WORKDIR /src
COPY pyproject.toml README.md ./
COPY kitti_eval ./kitti_eval
COPY server ./server
RUN pip install --no-cache-dir ".[server]" \
 && rm -rf /src

WORKDIR /data
USER kitti
# Compile every numba kernel into NUMBA_CACHE_DIR now (what the service's warm-up would), so a container
# starts warm (numba recompiles, once, if the host's CPU differs from the build machine's).
RUN python -m kitti_eval._jit --all

VOLUME ["/data"]
EXPOSE 8000
HEALTHCHECK --interval=30s --timeout=5s --start-period=60s --retries=3 \
    CMD ["python", "-c", "import sys, urllib.request; sys.exit(urllib.request.urlopen('http://127.0.0.1:8000/readyz', timeout=4).status != 200)"]
CMD ["uvicorn", "kitti_eval_server.main:app", "--host", "0.0.0.0", "--port", "8000", "--proxy-headers", "--timeout-graceful-shutdown", "10"]
