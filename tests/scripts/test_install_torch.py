"""The setup step's torch choice (scripts/install_torch.py), with and without a GPU visible."""

from __future__ import annotations

import http.server
import importlib.util
import os
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "install_torch.py"
spec = importlib.util.spec_from_file_location("install_torch", SCRIPT)
install_torch = importlib.util.module_from_spec(spec)
spec.loader.exec_module(install_torch)


def fake_smi(tmp_path: Path, output: str, code: int = 0) -> str:
    smi = tmp_path / "nvidia-smi"
    smi.write_text(f"#!/bin/sh\necho '{output}'\nexit {code}\n")
    smi.chmod(0o755)
    return str(smi)


def test_a_gpu_is_seen_by_its_device_node_or_nvidia_smi(tmp_path) -> None:
    no_dev = tmp_path / "dev"
    no_dev.mkdir()
    assert not install_torch.gpu_visible(nvidia_smi=str(tmp_path / "absent"), dev=no_dev)
    assert install_torch.gpu_visible(nvidia_smi=fake_smi(tmp_path, "GPU 0: NVIDIA H200 (UUID: x)"), dev=no_dev)
    # a driver without a device: nvidia-smi fails
    assert not install_torch.gpu_visible(
        nvidia_smi=fake_smi(tmp_path, "NVIDIA-SMI has failed", code=9), dev=no_dev)
    (no_dev / "nvidia0").touch()
    assert install_torch.gpu_visible(nvidia_smi=str(tmp_path / "absent"), dev=no_dev)


@pytest.mark.parametrize("variant, gpu, index_up, expected", [
    ("auto", False, True, ["--index-url", install_torch.CPU_INDEX]),
    ("auto", True, True, []),
    ("auto", False, False, []),  # offline: the default index (a mirror or a local wheel folder)
    ("cpu", True, True, ["--index-url", install_torch.CPU_INDEX]),
    ("cuda", False, True, []),
])
def test_the_index_follows_the_gpu(variant, gpu, index_up, expected) -> None:
    args, why = install_torch.choose(variant, lambda: gpu, lambda _url: index_up)
    assert args == expected
    assert ("CUDA" in why) == (expected == [] and (gpu or variant == "cuda"))


def test_a_bad_variant_is_one_line(tmp_path) -> None:
    run = subprocess.run([sys.executable, str(SCRIPT), "--dry-run"], capture_output=True, text=True,
                         env={**os.environ, "COGEXPLORE_TORCH": "rocm"})
    assert run.returncode == 2 and run.stderr.strip().startswith("error: torch variant must be one of")


def test_dry_run_prints_the_pinned_command() -> None:
    run = subprocess.run([sys.executable, str(SCRIPT), "--dry-run", "--variant", "cuda"],
                         capture_output=True, text=True, check=True)
    assert run.stdout.split()[-1] == install_torch.TORCH_PIN and "--index-url" not in run.stdout
    assert "CUDA build" in run.stderr


def test_reachable_answers_for_a_real_server_and_not_for_a_closed_port() -> None:
    server = http.server.HTTPServer(("127.0.0.1", 0), http.server.SimpleHTTPRequestHandler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        assert install_torch.reachable(f"http://127.0.0.1:{server.server_port}/no-such-page")  # 404 is there
    finally:
        server.shutdown()
        server.server_close()
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        closed = s.getsockname()[1]
    assert not install_torch.reachable(f"http://127.0.0.1:{closed}/", timeout_s=2.0)
