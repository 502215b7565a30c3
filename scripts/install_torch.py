#!/usr/bin/env python3
"""Install the pinned torch build this machine should run: ``python scripts/install_torch.py``.

PyPI's Linux wheel of torch is the CUDA build (a 500 MB wheel plus several GB of CUDA, cuDNN and
NCCL). A machine with no NVIDIA GPU gains nothing from it, so it gets the CPU build from
PyTorch's CPU wheel index; a machine with one gets PyPI's CUDA build. Where the CPU index cannot
be reached (an offline machine with a local wheel folder or a mirror), pip's default index is
used. ``COGEXPLORE_TORCH=cpu|cuda|auto`` (or ``--variant``) overrides the detection.

Standard library only: it runs before anything is installed (the Makefile, the Dockerfile and
the README's remote-actor setup call it with the interpreter that should get torch).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import urllib.error
import urllib.request
from pathlib import Path
from typing import Callable, Sequence

TORCH_PIN = "torch==2.13.0"
CPU_INDEX = "https://download.pytorch.org/whl/cpu"
VARIANTS = ("auto", "cpu", "cuda")


def gpu_visible(nvidia_smi: str | None = None, dev: Path = Path("/dev")) -> bool:
    """An NVIDIA GPU this process can use: a device node, or ``nvidia-smi -L`` listing one."""
    if any(dev.glob("nvidia[0-9]*")):
        return True
    smi = nvidia_smi or shutil.which("nvidia-smi")
    if not smi:
        return False
    try:
        listed = subprocess.run([smi, "-L"], capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.SubprocessError):
        return False
    return listed.returncode == 0 and "GPU" in listed.stdout


def reachable(url: str, timeout_s: float = 5.0) -> bool:
    """Whether an index answers at all (any HTTP status counts: it is there)."""
    try:
        with urllib.request.urlopen(urllib.request.Request(url, method="HEAD"), timeout=timeout_s):
            return True
    except urllib.error.HTTPError:
        return True
    except (OSError, ValueError):
        return False


def choose(variant: str, has_gpu: Callable[[], bool], index_reachable: Callable[[str], bool]
           ) -> tuple[list[str], str]:
    """pip's index arguments for ``variant`` and a sentence saying why."""
    if variant not in VARIANTS:
        raise ValueError(f"torch variant must be one of {', '.join(VARIANTS)}, got {variant!r}")
    if variant == "cuda" or (variant == "auto" and has_gpu()):
        why = "an NVIDIA GPU is visible" if variant == "auto" else "asked for"
        return [], f"CUDA build from the default index ({why})"
    why = "no NVIDIA GPU is visible" if variant == "auto" else "asked for"
    if index_reachable(CPU_INDEX):
        return ["--index-url", CPU_INDEX], f"CPU build from {CPU_INDEX} ({why})"
    return [], f"CPU build wanted ({why}), but {CPU_INDEX} is unreachable: pip's default index"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variant", choices=VARIANTS, default=os.environ.get("COGEXPLORE_TORCH", "auto"),
                        help="cpu, cuda or auto (default: $COGEXPLORE_TORCH or auto: detect a GPU)")
    parser.add_argument("--dry-run", action="store_true", help="print the pip command, install nothing")
    args = parser.parse_args(argv)
    try:
        index_args, why = choose(args.variant, gpu_visible, reachable)
    except ValueError as exc:  # a bad $COGEXPLORE_TORCH
        print(f"error: {exc}", file=sys.stderr)
        return 2
    command = [sys.executable, "-m", "pip", "install", "--quiet", TORCH_PIN, *index_args]
    print(f"torch: {why}", file=sys.stderr, flush=True)
    if args.dry_run:
        print(" ".join(command))
        return 0
    return subprocess.call(command)


if __name__ == "__main__":
    sys.exit(main())
