# syntax=docker/dockerfile:1
# Fundamental-forms mesh service: FastAPI app served by uvicorn. Build/run: docs/deployment.md.
FROM python:3.11-slim

# WEB_CONCURRENCY=1 pins uvicorn to one worker: the app runs its own solver process pool,
# sized by its settings (environment variables documented in README.md).
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    WEB_CONCURRENCY=1

RUN groupadd --system --gid 10001 app \
    && useradd --system --uid 10001 --gid app --create-home --home-dir /home/app \
       --shell /usr/sbin/nologin app

WORKDIR /app

# Runtime dependencies first, in their own layer (cached until pyproject.toml changes):
# exactly [project].dependencies, none of the test/dev extras.
COPY pyproject.toml README.md ./
RUN python -c "import tomllib; print('\n'.join(tomllib.load(open('pyproject.toml', 'rb'))['project']['dependencies']))" > /tmp/requirements.txt \
    && pip install --no-cache-dir -r /tmp/requirements.txt \
    && rm /tmp/requirements.txt

# The application code (owned by root, read-only for the service user).
COPY solver/ solver/
COPY service/ service/
RUN pip install --no-cache-dir --no-deps . \
    && python -m compileall -q solver service \
    && rm -rf build ./*.egg-info

USER 10001:10001
EXPOSE 8000

HEALTHCHECK --interval=30s --timeout=5s --start-period=30s --retries=3 \
    CMD ["python", "-c", "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=4)"]

CMD ["uvicorn", "service.app:app", "--host", "0.0.0.0", "--port", "8000"]
