# syntax=docker/dockerfile:1
# Fundamental-forms mesh service (python -m service: FastAPI on uvicorn). Build/run: docs/deployment.md.
# Verified end to end (build, API, web page, compose topology) by scripts/docker-smoke.sh.

# The web page's three.js modules: `npm ci --prefix web` installs them from the npm registry
# (committed lockfile) and web/build.mjs copies them to service/static/vendor/; only those
# copies reach the final image.
FROM node:20-bookworm-slim AS web
WORKDIR /src
COPY web/package.json web/package-lock.json web/build.mjs web/redoc-logo-mini.svg web/
RUN npm ci --prefix web --no-audit --no-fund

# The runtime dependencies in a virtual environment that the final stage copies whole:
# [project].dependencies plus the `dask` extra, none of the test/dev extras (the one image
# runs the API, the Dask scheduler and the Dask workers, docker-compose.yml). The venv has no
# pip/setuptools (the base image's pip installs into it). In the same step, so that nothing
# deleted reaches a layer: scripts/prune_mkl.py measures which MKL libraries a PARDISO
# factorization loads and deletes the rest of the ~1 GB oneAPI runtime that pypardiso's `mkl`
# wheel brings, then checks PARDISO still solves; NumPy's and SciPy's test suites, headers and
# the oneAPI wheels' build/offload files (cmake, pkgconfig, opt/compiler) go too.
FROM python:3.11-slim AS deps
ENV PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    MKL_ENABLE_INSTRUCTIONS=AVX2
WORKDIR /src
COPY pyproject.toml scripts/prune_mkl.py ./
RUN python -c "import tomllib; p = tomllib.load(open('pyproject.toml', 'rb'))['project']; print('\n'.join(p['dependencies'] + p['optional-dependencies']['dask']))" > requirements.txt \
    && python -m venv --without-pip /opt/ffs \
    && pip --python /opt/ffs/bin/python install --no-cache-dir --no-compile -r requirements.txt \
    && if /opt/ffs/bin/python -c "import pypardiso"; then /opt/ffs/bin/python prune_mkl.py; fi \
    && rm -rf /opt/ffs/lib/python3*/site-packages/numpy/*/tests \
              /opt/ffs/lib/python3*/site-packages/numpy/tests \
              /opt/ffs/lib/python3*/site-packages/scipy/*/tests \
              /opt/ffs/lib/python3*/site-packages/scipy/*/*/tests \
              /opt/ffs/share /opt/ffs/include /opt/ffs/opt /opt/ffs/lib/cmake /opt/ffs/lib/pkgconfig \
    && /opt/ffs/bin/python -m compileall -q -j 0 /opt/ffs/lib \
    && /opt/ffs/bin/python -c "import fastapi, uvicorn, numpy, scipy, trimesh, distributed"

FROM python:3.11-slim

# FFS_HOST/FFS_PORT: where `python -m service` (the CMD) listens. It runs one uvicorn process
# (the app runs its own solver process pool, sized by its settings: docs/service.md) with the
# deadline for request heads (FFS_HEADER_TIMEOUT, service.http.server) and without WebSocket
# per-message deflate, neither of which plain `uvicorn service.app:app` has.
# MKL_ENABLE_INSTRUCTIONS=AVX2: MKL's AVX2 kernels also on AVX-512 CPUs, because the image
# keeps only those and the generic ones (scripts/prune_mkl.py, docs/deployment.md).
# PYTHONPATH=/app: the application code is imported from /app by the service and by the Dask
# scheduler (--preload service.backends.dask) and workers alike.
ENV PATH=/opt/ffs/bin:$PATH \
    VIRTUAL_ENV=/opt/ffs \
    PYTHONPATH=/app \
    PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    FFS_HOST=0.0.0.0 \
    FFS_PORT=8000 \
    MKL_ENABLE_INSTRUCTIONS=AVX2

RUN groupadd --system --gid 10001 app \
    && useradd --system --uid 10001 --gid app --create-home --home-dir /home/app \
       --shell /usr/sbin/nologin app

# Dependencies first, in their own layer (cached until pyproject.toml changes).
COPY --from=deps /opt/ffs /opt/ffs

# The application code (owned by root, read-only for the service user), byte-compiled.
WORKDIR /app
COPY solver/ solver/
COPY service/ service/
# ffs_wire/: the binary body format the service shares with the client; ffs/: the command
# line and client (`ffs serve` runs this service as `python -m service`).
COPY ffs_wire/ ffs_wire/
COPY ffs/ ffs/
COPY --from=web /src/service/static/vendor/ service/static/vendor/
RUN python -m compileall -q solver service ffs_wire ffs

USER 10001:10001
# 8000: the API; 8786/8787: the Dask scheduler and its dashboard (docker-compose.yml).
EXPOSE 8000 8786 8787

HEALTHCHECK --interval=30s --timeout=5s --start-period=30s --retries=3 \
    CMD ["python", "-c", "import os, urllib.request; urllib.request.urlopen('http://127.0.0.1:%s/healthz' % os.environ.get('FFS_PORT', '8000'), timeout=4)"]

CMD ["python", "-m", "service"]
