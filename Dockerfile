# regtree: the API server with embedded workers (`regtree serve`), SQLite in a volume.
#   docker build -t regtree .
#   docker run -p 8000:8000 -v regtree-data:/app/var regtree
# Settings are REGTREE_* environment variables (service/core/config.py), e.g.
#   -e REGTREE_API_KEY=... -e REGTREE_EMBEDDED_WORKERS=2
#   -e REGTREE_DATABASE_URL=postgresql+psycopg://user:password@host/db   (PostgreSQL)
# More workers (same database: PostgreSQL, or this volume on one host):
#   docker run ... regtree regtree worker
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

WORKDIR /app

# A CJK font, so that pictures draw CJK shape names (glyph archives) instead of boxes.
RUN apt-get update \
    && apt-get install -y --no-install-recommends fonts-noto-cjk \
    && rm -rf /var/lib/apt/lists/*

# Same install as the README's demo (the server extra; here not editable, and with the
# postgres extra too, so that a PostgreSQL REGTREE_DATABASE_URL works). The migrations are
# not part of the package: they are copied beside it.
COPY pyproject.toml README.md alembic.ini ./
COPY registration ./registration
COPY service ./service
COPY migrations ./migrations
COPY setup.py ./
# A C compiler for the install only: CPD's compiled E-step passes (setup.py; without it
# the library would run numpy's slower passes), then removed again.
RUN apt-get update \
    && apt-get install -y --no-install-recommends gcc libc6-dev \
    && pip install '.[server,postgres]' \
    && python -I -c "import registration._cpd._ckernel" \
    && apt-get purge -y --auto-remove gcc libc6-dev \
    && rm -rf /var/lib/apt/lists/* \
    && useradd --create-home --uid 10001 regtree \
    && mkdir -p /app/var \
    && chown regtree /app/var

USER regtree
# The migrations folder is not part of the installed package: point the CLI at it.
ENV REGTREE_DATABASE_URL=sqlite:////app/var/regtree.sqlite \
    REGTREE_MIGRATIONS_DIR=/app/migrations \
    OMP_NUM_THREADS=1 \
    OPENBLAS_NUM_THREADS=1 \
    MKL_NUM_THREADS=1
VOLUME ["/app/var"]
EXPOSE 8000

HEALTHCHECK --interval=30s --timeout=5s --start-period=20s \
    CMD python -c "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=3)"

# Applies migrations, starts REGTREE_EMBEDDED_WORKERS worker processes, serves the API. On
# `docker stop` (SIGTERM) the workers give their running jobs back to the queue at once.
CMD ["regtree", "serve", "--host", "0.0.0.0", "--port", "8000"]
