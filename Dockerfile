# One image for every service; compose.yaml picks the subcommand.
FROM python:3.11-slim
ENV PYTHONUNBUFFERED=1 MPLBACKEND=Agg
WORKDIR /app
COPY pyproject.toml README.md ./
COPY shared ./shared
COPY services ./services
RUN pip install --no-cache-dir .
ENTRYPOINT ["autotune"]
