"""The API process never imports torch: not at import, not while serving uploads, scenes, jobs and queries.

Checked in a fresh interpreter, because this test session itself imports torch elsewhere.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from service.db.migrate import REPO_ROOT

SCRIPT = r"""
import json, sys
from pathlib import Path
sys.path.insert(0, {helpers!r})
steps = {{}}

def mark(step):
    steps[step] = "torch" in sys.modules

from fastapi.testclient import TestClient
from svc_helpers import RecordingSender, make_scene, new_key, pack, write_tiny_bundle
from service.db.migrate import upgrade
from service.main import create_app
from service.settings import Settings
mark("import")
settings = Settings(_env_file=None, data_dir=Path({tmp!r}) / "data")
settings.ensure_dirs()
upgrade(settings.database)
bundle = pack(write_tiny_bundle(Path({tmp!r}) / "bundle"))
mark("setup")
with TestClient(create_app(settings, sender=RecordingSender(), run_reaper=False)) as client:
    auth = new_key(settings)
    client.get("/readyz")
    scene = make_scene(client, auth, bundle)
    mark("scene")
    job = client.post("/v1/jobs", json={{"scene_id": scene["id"], "config": {{}}}}, headers=auth).json()
    client.get(f"/v1/jobs/{{job['id']}}", headers=auth)
    mark("job")
print(json.dumps(steps))
"""


def test_api_never_imports_torch(tmp_path: Path) -> None:
    helpers = str(Path(__file__).parent)
    code = SCRIPT.format(helpers=helpers, tmp=str(tmp_path))
    argv = [sys.executable, "-c", code]
    done = subprocess.run(argv, cwd=REPO_ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    steps = json.loads(done.stdout.strip().splitlines()[-1])
    assert not steps["import"], "importing service.main imported torch"
    assert not steps["scene"], "validating a bundle imported torch"
    assert not steps["job"], "creating or reading a job imported torch"
