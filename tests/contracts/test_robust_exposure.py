"""Exposure and sharing: what a local sweep opens to the network, and the modes of what commands write.

* The local dask cluster's dashboard (an unauthenticated web page that can see and stop tasks)
  used to listen on every interface (``dashboard_address=":0"``); now nothing of a local sweep
  listens beyond the loopback interface unless ``--dashboard`` asks for it.
* Outputs follow the umask: under 022 files are 0644 and folders 0755 (staged outputs were
  created 0700 / 0600 by ``tempfile`` whatever the umask).
"""

from __future__ import annotations

import os
import stat

import pytest

from elastimap.errors import UserError

_LISTEN = """
import json, os, psutil
from elastimap.sweep.cluster import local_cluster

if __name__ == "__main__":
    cluster = local_cluster(1)
    try:
        ips = {c.laddr.ip for c in psutil.Process().net_connections("inet") if c.status == psutil.CONN_LISTEN}
        print(json.dumps(sorted(ips)))
    finally:
        cluster.close()
"""


def test_local_cluster_listens_on_loopback_only(tmp_path):
    """In a fresh process (other tests' clusters may still listen in this one)."""
    import json
    import subprocess
    import sys

    script = tmp_path / "listen.py"
    script.write_text(_LISTEN)
    r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    ips = set(json.loads(r.stdout.strip().splitlines()[-1]))
    assert ips and ips <= {"127.0.0.1", "::1"}, ips


def test_dashboard_address_is_checked():
    from elastimap.sweep.run import SweepConfig

    with pytest.raises(UserError, match="dashboard"):
        SweepConfig(n=1, dashboard="8787").validate()
    SweepConfig(n=1, dashboard="127.0.0.1:8787").validate()


def _modes(root) -> dict[str, int]:
    out = {}
    for dirpath, dirs, files in os.walk(root):
        for name in dirs + files:
            p = os.path.join(dirpath, name)
            out[os.path.relpath(p, root)] = stat.S_IMODE(os.lstat(p).st_mode)
    return out


@pytest.fixture
def umask022():
    old = os.umask(0o022)
    try:
        yield
    finally:
        os.umask(old)


def test_staged_dir_and_atomic_file_follow_umask(tmp_path, umask022):
    from elastimap.outputs import staged_dir, write_text

    with staged_dir(tmp_path / "run", "out") as tmp:
        (tmp / "a.txt").write_text("x")
        (tmp / "sub").mkdir()
    write_text(tmp_path / "f.json", "{}", "out")
    assert stat.S_IMODE((tmp_path / "run").stat().st_mode) == 0o755
    assert stat.S_IMODE((tmp_path / "f.json").stat().st_mode) == 0o644
    assert _modes(tmp_path / "run") == {"a.txt": 0o644, "sub": 0o755}
