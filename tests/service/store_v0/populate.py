"""Store models and jobs through the service of an earlier commit (run by make.sh with that
commit's tree first on the path), then write what it answered to expected.json.

    python populate.py SRC DATA_DIR EXPECTED_JSON
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

src, data_dir, expected_path = Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3])

import service  # noqa: E402

assert Path(service.__file__).resolve().is_relative_to(src.resolve()), f"not the archived code: {service.__file__}"

from client import PHDClient  # noqa: E402
from phd_core.renderers.gs3d import write_ply  # noqa: E402
from phd_core.renderers.nerf import NeRFConfig, NeRFRenderer, RadianceField, save_nerf  # noqa: E402
from service.runner import BackgroundServer  # noqa: E402
from service.settings import Settings  # noqa: E402
from support.fixtures import svc_cameras, svc_random_gaussians  # noqa: E402

ADMIN, ALICE = "admin-key-for-the-fixture", "alice-key-for-the-fixture"
files = data_dir.parent / "files"
files.mkdir(parents=True)
keys = files / "keys.json"
keys.write_text(json.dumps({"alice": ALICE}))
write_ply(svc_random_gaussians(40, seed=0), files / "a.ply")
write_ply(svc_random_gaussians(30, seed=1), files / "c.ply")
config = NeRFConfig(depth=2, width=8, color_width=4, pos_freqs=2, dir_freqs=1, samples=8, grid_resolution=4,
                    bounds=[[-1, -1, -1], [1, 1, 1]], near=1.0, far=5.0)
save_nerf(NeRFRenderer(RadianceField(config, seed=0), training_cameras=svc_cameras(2, size=8)), files / "b.nerf")

train, views = svc_cameras(3, size=8), svc_cameras(2, size=8, phase=0.5)
jobs = []
with BackgroundServer(Settings(data_dir=data_dir, api_key=ADMIN, keys_file=keys)) as server:
    with PHDClient(server.url, api_key=ADMIN) as admin, PHDClient(server.url, api_key=ALICE) as alice:
        a = admin.upload_model(files / "a.ply", cameras=train, name="splats a")
        b = admin.upload_model(files / "b.nerf", name="tiny nerf")
        c = alice.upload_model(files / "c.ply", cameras=train, name="alice's splats", background="black")
        admin.calibrate(a.id, epsilon=0.5, step=0.5, samples=2)
        ranked = admin.rank(a.id, views, samples=2, heatmaps="files", run_async=True, wait=False)
        admin.wait_job(ranked.id)
        selected = alice.select(c.id, c.id, views, samples=2, ratio_a=0.1, ratio_b=0.2, rule="sigma_mean",
                                images="files", run_async=True, wait=False)
        alice.wait_job(selected.id)
        failed = admin.calibrate(b.id, epsilon=1e-9, step=0.5, samples=2, run_async=True, wait=False)
        try:
            admin.wait_job(failed.id)
        except Exception:
            pass
        models = [m.model_dump(mode="json") for m in admin.list_models()]
        answered = {}
        for job_id in (ranked.id, selected.id, failed.id):
            job = admin.get_job(job_id)
            answered[job_id] = {"job": job.model_dump(mode="json"), "artifacts": {
                name: hashlib.sha256(admin.download(f"/v1/jobs/{job_id}/artifacts/{name}")).hexdigest()
                for name in job.artifacts}}
        owners = {a.id: "admin", b.id: "admin", c.id: "alice"}

expected_path.write_text(json.dumps({"admin_key": ADMIN, "keys": {"alice": ALICE}, "models": models,
                                     "owners": owners, "jobs": answered}, indent=1, sort_keys=True) + "\n")
print(f"stored {len(models)} models and {len(answered)} jobs in {data_dir}")
