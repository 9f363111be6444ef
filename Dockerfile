# FreeScale worker / flow image (CPU). Build: docker build -t freescale:latest .
FROM python:3.11-slim
ENV PIP_NO_CACHE_DIR=1 PYTHONUNBUFFERED=1 PREFECT_SERVER_ANALYTICS_ENABLED=false \
    DO_NOT_TRACK=1 FREESCALE_HOME=/app MPLBACKEND=Agg
RUN apt-get update && apt-get install -y --no-install-recommends libgl1 libglib2.0-0 \
    && rm -rf /var/lib/apt/lists/*
WORKDIR /app
COPY pyproject.toml README.md constraints.txt ./
COPY freescale_core ./freescale_core
COPY schemas ./schemas
COPY tasks ./tasks
COPY flows ./flows
COPY prefect.yaml ./
# torch is pinned to the CPU build in pyproject.toml; the CPU index keeps CUDA wheels out;
# constraints.txt pins every other dependency to the versions the tests and benchmarks ran on.
RUN pip install -c constraints.txt --extra-index-url https://download.pytorch.org/whl/cpu -e .
ENTRYPOINT ["freescale"]
CMD ["--help"]
