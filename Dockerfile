# syntax=docker/dockerfile:1
# Fundamental-forms mesh service: FastAPI app served by uvicorn. Build/run: docs/deployment.md.

# The web page's three.js modules: `npm ci --prefix web` installs them from the npm registry
# (committed lockfile) and web/build.mjs copies them to service/static/vendor/; only those
# copies reach the final image.
FROM node:20-bookworm-slim AS web
WORKDIR /src
COPY web/package.json web/package-lock.json web/build.mjs web/
RUN npm ci --prefix web --no-audit --no-fund

FROM python:3.11-slim

# WEB_CONCURRENCY=1 pins uvicorn to one worker: the app runs its own solver process pool,
# sized by its settings (environment variables documented in README.md).
# UVICORN_WS_PER_MESSAGE_DEFLATE=false: session WebSockets carry float32 vertex buffers,
# which barely compress; deflating them costs ~5 ms per 20K-face reply (docs/service.md).
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    WEB_CONCURRENCY=1 \
    UVICORN_WS_PER_MESSAGE_DEFLATE=false

RUN groupadd --system --gid 10001 app \
    && useradd --system --uid 10001 --gid app --create-home --home-dir /home/app \
       --shell /usr/sbin/nologin app

WORKDIR /app

# Runtime dependencies first, in their own layer (cached until pyproject.toml changes):
# [project].dependencies plus the `dask` extra, none of the test/dev extras. The one image
# runs the API, the Dask scheduler and the Dask workers (docker-compose.yml).
COPY pyproject.toml README.md ./
RUN python -c "import tomllib; p = tomllib.load(open('pyproject.toml', 'rb'))['project']; print('\n'.join(p['dependencies'] + p['optional-dependencies']['dask']))" > /tmp/requirements.txt \
    && pip install --no-cache-dir -r /tmp/requirements.txt \
    && rm /tmp/requirements.txt

# The application code (owned by root, read-only for the service user).
COPY solver/ solver/
COPY service/ service/
COPY --from=web /src/service/static/vendor/ service/static/vendor/
RUN pip install --no-cache-dir --no-deps . \
    && python -m compileall -q solver service \
    && rm -rf build ./*.egg-info

USER 10001:10001
# 8000: the API; 8786/8787: the Dask scheduler and its dashboard (docker-compose.yml).
EXPOSE 8000 8786 8787

HEALTHCHECK --interval=30s --timeout=5s --start-period=30s --retries=3 \
    CMD ["python", "-c", "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=4)"]

CMD ["uvicorn", "service.app:app", "--host", "0.0.0.0", "--port", "8000"]
