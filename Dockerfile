# PHiM detection server, GPU image. Build: docker build -t phim-server .
# Run:   docker run --gpus all -p 8080:8080 -e PHIM_AUTH_TOKENS=/run/secrets/tokens -v ...:/run/secrets phim-server
# zenoh listens nowhere by default; for vehicles over zenoh add -p 7447:7447 -e PHIM_ZENOH_LISTEN=tls/0.0.0.0:7447
# -e PHIM_ZENOH_CONFIG_FILE=... (an ACL, mTLS or user/password: deploy/zenoh/; docs/security.md).
# The one place the image's torch and CUDA versions are named: the base image, whose CUDA build of PyTorch the
# install keeps. Every other dependency is pinned by constraints.txt (scripts/lock.sh), as in CI.
ARG BASE_IMAGE=pytorch/pytorch:2.5.1-cuda12.4-cudnn9-runtime
FROM ${BASE_IMAGE}

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

# Triton (the GPU scan and sparse-conv kernels, model/ops/*_triton.py) builds each kernel's launcher with the
# system C compiler at first use; the runtime base image has none (without one the torch paths run instead).
RUN apt-get update \
 && apt-get install -y --no-install-recommends gcc libc6-dev \
 && rm -rf /var/lib/apt/lists/*

WORKDIR /opt/phim
COPY pyproject.toml README.md LICENSE constraints.txt ./
COPY contract ./contract
COPY lidar ./lidar
COPY ros ./ros
COPY phim ./phim
COPY model ./model
COPY server ./server
COPY clients ./clients

# Install the package and its server extras at the pinned versions, without touching the base image's torch.
RUN pip freeze | grep -i '^torch==' > /tmp/torch-constraint.txt \
 && pip install -c constraints.txt -c /tmp/torch-constraint.txt ".[server,ros2]" \
 && python -c "import torch, fastapi, zenoh; print('torch', torch.__version__, 'cuda', torch.version.cuda)"

# Weights inside the image: the shipped default model (model/weights/tiny-sim.pt) as a checkpoint file.
RUN python -m server.default_model --out /opt/phim/weights/phim-default.pt

RUN useradd --create-home --uid 10001 phim
USER phim

ENV PHIM_CHECKPOINT=/opt/phim/weights/phim-default.pt \
    PHIM_PORT=8080 \
    PHIM_DEVICE=auto \
    PHIM_ZENOH_LISTEN=""
EXPOSE 8080 7447

HEALTHCHECK --interval=10s --timeout=5s --start-period=120s --retries=3 \
    CMD ["python", "-m", "server.healthcheck"]

# SIGTERM (docker stop): stop taking sectors, answer those in flight, exit 0. Give it time: docker stop -t 30.
# Binding 0.0.0.0 needs a token file (PHIM_AUTH_TOKENS, mounted; `phim auth add-token`) or PHIM_INSECURE=1:
# without either the server refuses to start (docs/security.md).
STOPSIGNAL SIGTERM
CMD ["phim", "serve", "--host", "0.0.0.0"]
