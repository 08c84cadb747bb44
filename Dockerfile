# PH-Dropout service: small CPU image running `phd serve`.
#
#   docker build -t ph-dropout-service .
#   docker run -p 8000:8000 -v phd-data:/data ph-dropout-service
#   docker run -p 8000:8000 -v phd-data:/data -e PHD_API_KEY=secret ph-dropout-service --workers 2
#   docker build --build-arg EXTRAS='[ray]' -t ph-dropout-service:ray .    # jobs on Ray: docs/scale-out.md
#
# It installs what the README's set-up installs: torch==2.13.0 (here the CPU build from
# PyTorch's CPU wheel index, so no CUDA libraries), then the project itself.
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

WORKDIR /app
RUN pip install torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu

COPY pyproject.toml README.md ./
COPY phd_core ./phd_core
COPY phd_cli ./phd_cli
COPY service ./service
COPY client ./client
ARG EXTRAS=""
RUN pip install ".${EXTRAS}" \
    && useradd --create-home --uid 10001 phd \
    && mkdir -p /data \
    && chown phd:phd /data

USER phd
# OMP_WAIT_POLICY=PASSIVE: idle OpenMP threads sleep instead of spinning, which keeps worker
# threads from starving each other on few or shared cores (docs/service.md, "Benchmark").
# NUMBA_CACHE_DIR: the compiled render kernels are cached where the service user may write
# (site-packages is root's), so only the first render after a fresh container compiles them.
ENV PHD_DATA_DIR=/data \
    OMP_WAIT_POLICY=PASSIVE \
    NUMBA_CACHE_DIR=/home/phd/.cache/numba
VOLUME ["/data"]
EXPOSE 8000

HEALTHCHECK --interval=30s --timeout=5s --start-period=30s --retries=3 \
    CMD ["python", "-c", "import sys, urllib.request; sys.exit(urllib.request.urlopen('http://127.0.0.1:8000/health', timeout=4).status != 200)"]

# Extra arguments of `docker run IMAGE ...` are appended (e.g. --workers 2).
ENTRYPOINT ["phd", "serve", "--host", "0.0.0.0", "--port", "8000", "--data-dir", "/data"]
