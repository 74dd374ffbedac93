# One image for gateway and worker (the command differs), installed by the same script the tests run.
FROM python:3.11-slim

# CPU wheels: the image must not pull CUDA; the GPU profile in docker-compose.yml overrides this build arg.
ARG TORCH_INDEX=https://download.pytorch.org/whl/cpu
ENV TORCH_INDEX=${TORCH_INDEX} \
    PRECOND_EXTRAS=model \
    PRECOND_INSTALL_REDIS=0 \
    PIP_NO_CACHE_DIR=1 \
    PYTHONUNBUFFERED=1 \
    PATH=/app/.venv/bin:$PATH \
    MODEL_CACHE_DIR=/models

# libseccomp: the sandbox's kernel policy (the workers refuse untrusted code without it).
RUN apt-get update && apt-get install -y --no-install-recommends libseccomp2 && rm -rf /var/lib/apt/lists/*

WORKDIR /app
COPY pyproject.toml README.md* ./
COPY scripts/install.sh scripts/install.sh
COPY precond precond
COPY precond_client precond_client
COPY examples examples
COPY docker docker
RUN bash scripts/install.sh

# /secrets: where compose mounts the volume its `keys` service fills (an empty volume takes this ownership).
RUN useradd --create-home --uid 10001 precond && mkdir -p /models /secrets && chown precond /models /secrets
USER precond
EXPOSE 8000
CMD ["precond", "serve", "--host", "0.0.0.0", "--port", "8000"]
