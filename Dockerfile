# The cogexplore image: every service of docker-compose.yml (learner, actor, evaluator) and the
# Rerun web viewer run from it. Build: `docker compose build` (or `docker build -t cogexplore .`).
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    RERUN_ANALYTICS=0 \
    MUJOCO_GL=egl

# EGL and Mesa's software renderer: only MuJoCo's optional GL depth backend (backend = "gl") needs
# them; the default ray-cast backend renders without GL.
RUN apt-get update \
 && apt-get install -y --no-install-recommends libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri \
 && rm -rf /var/lib/apt/lists/*

# torch first, by scripts/install_torch.py: no GPU is visible while an image builds, so the
# variant is a build argument (cpu: PyTorch's CPU index; cuda: PyPI's CUDA build, for
# `docker compose build --build-arg TORCH_VARIANT=cuda` on a GPU host). Resolved through the
# project's pin instead, pip would pull the multi-GB CUDA build.
ARG TORCH_VARIANT=cpu
COPY scripts/install_torch.py /tmp/install_torch.py
RUN python /tmp/install_torch.py --variant "$TORCH_VARIANT" && rm /tmp/install_torch.py

WORKDIR /app

# Dependencies before sources, so that a code change does not download them again: install the
# project from its metadata with empty packages, then uninstall it and keep the dependencies.
# The metadata names README.md and LICENSE (license-files): setuptools refuses a pattern that
# matches nothing (a deprecation warning until 2027-02-18, an error afterwards).
COPY pyproject.toml README.md LICENSE ./
RUN mkdir shared services \
 && touch shared/__init__.py services/__init__.py \
 && pip install . \
 && pip uninstall -y cogexplore \
 && rm -rf shared services build cogexplore.egg-info

COPY . .
RUN pip install --no-deps . \
 && rm -rf build cogexplore.egg-info \
 && mkdir -p /app/runs \
 && cogexplore --help > /dev/null

# Services write runs/<run>/ here (the compose file mounts it; COGEXPLORE_RUNS_DIR points at it).
ENV COGEXPLORE_RUNS_DIR=/app/runs
CMD ["cogexplore", "--help"]
