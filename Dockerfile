# One image for every service; compose.yaml picks the subcommand. Runs as an unprivileged
# user (uid 1000 here; compose runs it as the invoking user's ${UID}:${GID}, any uid works:
# nothing is written outside /tmp and the mounted runs directory).
FROM python:3.11-slim
ENV PYTHONUNBUFFERED=1 PYTHONDONTWRITEBYTECODE=1 MPLBACKEND=Agg \
    HOME=/tmp MPLCONFIGDIR=/tmp/matplotlib
WORKDIR /app
COPY pyproject.toml README.md ./
COPY shared ./shared
COPY services ./services
RUN pip install --no-cache-dir . \
    && useradd --uid 1000 --user-group --no-create-home --shell /usr/sbin/nologin autotune
USER 1000:1000
ENTRYPOINT ["autotune"]
