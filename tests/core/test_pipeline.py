"""End to end: a tiny synthetic scene through every stage, the outputs, resume, queries and the CLI."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from torch_threads import one_torch_thread  # noqa: F401  (autouse fixture: the language field on a shared host)

from panogs_core.cli import main as cli_main
from panogs_core.errors import BundleError, Cancelled, InputError
from panogs_core.io.ply import read_ply_vertices
from panogs_core.io.run_folder import RUN_FILES, load_result
from panogs_core.language.query import query_instances
from panogs_core.pipeline.config import PipelineConfig
from panogs_core.pipeline.run import STAGES, run_pipeline
from panogs_core.synthetic import make_scene

# The CLIP label-set space needs no text encoder, which keeps this module fast.
SPACE = "clip-vit-b32"


@pytest.fixture(scope="module")
def tiny_bundle(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_scene(
        tmp_path_factory.mktemp("bundle") / "tiny", preset="tiny", difficulty="easy", seed=0, feature_space=SPACE
    )


# The run of the module: the default config but a shorter appearance fit. No label reads the fit (no other stage's
# checkpoint key includes it); 40 iterations raise the key frames' PSNR by 5.1 dB on this scene (23.8 -> 28.8,
# measured 2026-12-05; the default 220 by 8.7) at a fifth of the fit's time, which was two thirds of the run's.
# The tests that run this bundle again into the run's folder or from its checkpoints keep the same fit setting,
# so that the fit is reused. Every test that reads the run is marked slow.
FIT_ITERATIONS = 40
TINY_RUN_CONFIG = PipelineConfig().with_overrides({"appearance": {"iterations": FIT_ITERATIONS}})
TINY_RUN_FIT = ["--set", f"appearance.iterations={FIT_ITERATIONS}"]  # the same on the command line


@pytest.fixture(scope="module")
def tiny_run(tiny_bundle: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, object, list]:
    out = tmp_path_factory.mktemp("run")
    seen: list[tuple[str, int, int]] = []
    result = run_pipeline(tiny_bundle, out, TINY_RUN_CONFIG, on_progress=lambda s, d, t: seen.append((s, d, t)))
    return out, result, seen


@pytest.mark.slow
def test_outputs_written_and_consistent(tiny_run: tuple[Path, object, list]) -> None:
    out, result, _ = tiny_run
    for name in (
        "panoptic.ply",
        "labels.npz",
        "instances.json",
        "instance_features.npy",
        "gaussians.ply",
        "report.json",
        "metrics.json",
        "vocabulary.json",
    ):
        assert (out / name).is_file(), name
    ply = read_ply_vertices(out / "panoptic.ply")
    assert set(ply) >= {"x", "y", "z", "red", "green", "blue", "semantic", "instance"}
    labels = np.load(out / "labels.npz")
    n = result.num_primitives
    assert labels["semantic"].shape == labels["instance"].shape == ply["x"].shape == (n,)
    instances = json.loads((out / "instances.json").read_text())
    ids = {i["id"] for i in instances}
    assert set(np.unique(labels["instance"][labels["instance"] >= 0]).tolist()) == ids
    for inst in instances:  # each instance's points carry its class, and lie in its box
        member = labels["instance"] == inst["id"]
        assert member.sum() == inst["num_points"]
        assert np.all(labels["semantic"][member] == inst["class_index"])
        pts = np.stack([ply["x"], ply["y"], ply["z"]], 1)[member]
        assert np.all(pts >= np.array(inst["bbox_min"]) - 1e-5)
        assert np.all(pts <= np.array(inst["bbox_max"]) + 1e-5)
    gauss = read_ply_vertices(out / "gaussians.ply")
    assert {"f_dc_0", "opacity", "scale_0", "rot_0", "semantic"} <= set(gauss)


def test_colours_are_fused_only_for_primitives_without_their_own(tiny_bundle: Path) -> None:
    # The export takes the geometry's colours first: with them, the fusion reads no colour frame.
    import dataclasses

    from panogs_core.io.bundle import open_bundle
    from panogs_core.pipeline import stage_table as st

    scene, cfg = open_bundle(tiny_bundle), PipelineConfig()
    prims = st.primitives(scene, cfg, lambda *_: None)
    vis = st.visibility(scene, prims, cfg, lambda *_: None)
    assert prims.colors is not None
    assert st.fusion(scene, vis, prims, cfg, lambda *_: None).colors is None
    fused = st.fusion(scene, vis, dataclasses.replace(prims, colors=None), cfg, lambda *_: None)
    assert fused.colors is not None
    assert fused.colors.shape == (prims.points.shape[0], 3)


@pytest.mark.slow  # reads tiny_run, a whole pipeline run
def test_the_run_folder_holds_what_its_declaration_lists(tiny_run: tuple[Path, object, list]) -> None:
    """Every file the exporter and the pipeline write is declared, and every file a run always has is there."""
    out, result, _ = tiny_run
    declared = {spec.name.rstrip("/"): spec for spec in RUN_FILES}
    written = {path.name: path.is_dir() for path in out.iterdir()}
    undeclared = sorted(set(written) - set(declared))
    assert undeclared == [], f"written but not declared in panogs_core/io/run_folder.py: {undeclared}"
    assert set(result.files) <= {spec.name for spec in RUN_FILES if not spec.is_folder}
    for name, is_dir in written.items():
        assert is_dir == declared[name].is_folder, name
    missing = sorted(name for name, spec in declared.items() if not spec.optional and name not in written)
    assert missing == [], f"declared as always written, but absent: {missing}"


@pytest.mark.slow
def test_report_has_every_stage(tiny_run: tuple[Path, object, list]) -> None:
    out, _, seen = tiny_run
    report = json.loads((out / "report.json").read_text())
    assert [s["stage"] for s in report["stages"]] == list(STAGES)
    assert all(s["wall_s"] >= 0 and s["peak_rss_mb"] > 0 for s in report["stages"])
    assert len(report["input_sha256"]) == 64
    assert PipelineConfig.from_dict(report["config"]) == TINY_RUN_CONFIG
    assert {s for s, _, _ in seen} == set(STAGES)  # progress reached the caller for every stage


@pytest.mark.slow
def test_metric_floors_on_tiny_easy(tiny_run: tuple[Path, object, list]) -> None:
    """Floors well below what the method reaches, so they catch breakage, not noise."""
    _, result, _ = tiny_run
    m = result.metrics["standard"]
    # measured on this scene: mIoU 0.86, PRQ(T) 0.81, PRQ(S) 0.97
    assert m["miou"] >= 0.75
    assert m["prq_thing"] >= 0.65
    assert m["prq_stuff"] >= 0.85
    assert result.metrics["paper"]["miou"] == pytest.approx(m["miou"], abs=0.2)


@pytest.mark.slow
def test_resume_reuses_checkpoints_and_reruns_changed_stages(
    tiny_bundle: Path, tiny_run: tuple[Path, object, list]
) -> None:
    out, first, _ = tiny_run
    cfg = TINY_RUN_CONFIG.with_overrides({"clustering": {"thresholds": [0.9, 0.75, 0.6]}})
    again = run_pipeline(tiny_bundle, out, cfg)
    cached = {t.name: t.cached for t in again.timings}
    assert [cached[s] for s in ("appearance", "fusion", "language_field", "superprimitives")] == [True] * 4
    assert [cached[s] for s in ("clustering", "labeling")] == [False, False]
    restored = run_pipeline(tiny_bundle, out, TINY_RUN_CONFIG)  # back to the first run's: its labels
    assert restored.instances == first.instances


@pytest.mark.slow
def test_a_run_stopped_in_the_appearance_fit_resumes_there(
    tiny_bundle: Path, tiny_run: tuple[Path, object, list], tmp_path: Path
) -> None:
    out, first, _ = tiny_run
    # Every stage but the fit (its settings differ here) comes from the first run's checkpoints.
    shutil.copytree(out / "stages", tmp_path / "stages")
    seen: list[tuple[str, int]] = []

    def stop_in_the_fit(stage: str, done: int, total: int) -> None:
        seen.append((stage, done))
        if stage == "appearance" and done == 4:
            raise Cancelled("worker shutting down")

    short_fit = PipelineConfig().with_overrides({"appearance": {"iterations": 10}})
    with pytest.raises(Cancelled):
        run_pipeline(tiny_bundle, tmp_path, short_fit, on_progress=stop_in_the_fit)
    assert (tmp_path / "stages" / "appearance.partial.pt").is_file()
    seen.clear()
    resumed = run_pipeline(tiny_bundle, tmp_path, short_fit, on_progress=lambda s, d, t: seen.append((s, d)))
    fit_steps = [d for s, d in seen if s == "appearance" and d > 0]
    assert fit_steps[:2] == [5, 6], "the fit goes on from iteration 5"
    assert fit_steps[-1] == 10
    assert not (tmp_path / "stages" / "appearance.partial.pt").exists(), "the snapshot goes once the stage is done"
    assert resumed.instances == first.instances
    assert resumed.appearance["iterations"] == 10


@pytest.mark.slow
def test_settings_of_one_stage_do_not_redo_the_mask_lookup_or_the_graph_cut(
    tiny_bundle: Path, tiny_run: tuple[Path, object, list]
) -> None:
    out, first, _ = tiny_run
    # The affinity's aggregate is read by the clustering only, chunk_rows bounds its memory only; both sit in
    # the YAML section that also holds the mask look-ups' settings.
    measure_only = TINY_RUN_CONFIG.with_overrides({"affinity": {"aggregate": "mean", "chunk_rows": 5000}})
    cached = {t.name: t.cached for t in run_pipeline(tiny_bundle, out, measure_only).timings}
    assert [cached[s] for s in ("masks", "neighbors", "superprimitives")] == [True] * 3
    assert cached["clustering"] is False
    lookup = TINY_RUN_CONFIG.with_overrides({"affinity": {"mask_depth_mad": 3.0}})  # read by the look-ups
    cached = {t.name: t.cached for t in run_pipeline(tiny_bundle, out, lookup).timings}
    assert [cached[s] for s in ("fusion", "neighbors")] == [True, True]
    assert [cached[s] for s in ("masks", "superprimitives", "clustering")] == [False] * 3
    assert run_pipeline(tiny_bundle, out, TINY_RUN_CONFIG).instances == first.instances


@pytest.mark.slow
def test_query_by_class_name_returns_instances_of_that_class(tiny_run: tuple[Path, object, list]) -> None:
    out, _, _ = tiny_run
    loaded = load_result(out)
    things = [i for i in loaded.instances if i.kind == "thing"]
    assert things
    target = things[0].class_name
    hits = query_instances(
        loaded.instances, loaded.vocabulary, target, feature_space=loaded.feature_space, top_k=50, min_score=0.5
    )
    assert hits
    assert {h.class_name for h in hits} == {target}
    expected = {i.id for i in loaded.instances if i.class_name == target}
    assert {h.instance_id for h in hits} <= expected


def test_invalid_bundle_is_refused_before_any_work(tiny_bundle: Path, tmp_path: Path) -> None:
    import shutil

    broken = tmp_path / "broken"
    shutil.copytree(tiny_bundle, broken)
    (broken / "depth" / "000003.png").write_bytes(b"not a png")
    manifest = json.loads((broken / "scene.json").read_text())
    manifest["frames"][1]["pose"][0][0] = float("nan")
    (broken / "scene.json").write_text(json.dumps(manifest))
    with pytest.raises(BundleError) as info:
        run_pipeline(broken, tmp_path / "out")
    assert len(info.value.problems) >= 2
    assert not (tmp_path / "out" / "labels.npz").exists()


@pytest.mark.slow
def test_cli_run_and_query(
    tiny_bundle: Path, tiny_run: tuple[Path, object, list], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import shutil

    out = tmp_path / "cli-run"
    shutil.copytree(tiny_run[0] / "stages", out / "stages")  # the CLI resumes from the library run's checkpoints
    argv = ["run", str(tiny_bundle), "--out", str(out), "-q", *TINY_RUN_FIT]
    assert cli_main([*argv, "--set", "clustering.thresholds=[0.9,0.8,0.7,0.6]"]) == 0
    printed = capsys.readouterr().out
    assert "instances" in printed
    assert "mIoU" in printed
    assert "gaussians: PSNR" in printed
    assert cli_main(["query", str(out), "wall"]) == 0
    assert "wall" in capsys.readouterr().out


def test_cli_reports_user_errors_cleanly(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["run", str(tmp_path / "missing"), "--out", str(tmp_path / "o"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "missing" in err
    assert "Traceback" not in err
    assert cli_main(["run", str(tmp_path), "--out", str(tmp_path / "o"), "-q", "--set", "clustring.x=1"]) == 2
    assert "unknown key" in capsys.readouterr().err


@pytest.mark.slow
def test_the_gaussian_scene_is_fitted_reported_and_renders(tiny_run: tuple[Path, object, list], tmp_path: Path) -> None:
    out, _, _ = tiny_run
    report = json.loads((out / "report.json").read_text())
    fit = report["appearance"]
    assert fit["fitted"]
    assert fit["psnr_after"] > fit["psnr_before"] + 3.0  # the fit improves the renders of the key frames
    assert fit["frames_without_color"] == []
    assert {s["stage"]: s["device"] for s in report["stages"]}["appearance"] == "cpu"
    gauss = read_ply_vertices(out / "gaussians.ply")
    assert float(np.mean(gauss["opacity"])) != 0.0  # no longer the initial logit 0 everywhere
    assert (out / "cameras.json").is_file()
    frame = json.loads((out / "cameras.json").read_text())["frames"][0]["id"]
    assert cli_main(["render", str(out), "--frame", frame, "--out", str(tmp_path)]) == 0
    assert (tmp_path / "panoptic.png").is_file()


def _renamed_vocabulary(bundle: Path, folder: Path) -> Path:
    """The bundle's vocabulary.json with every class renamed (same order, kinds and embeddings), in ``folder``."""
    doc = json.loads((bundle / "vocabulary.json").read_text())
    for entry in doc["classes"]:
        entry["name"] = f"my {entry['name']}"
    folder.mkdir(parents=True)
    shutil.copy(bundle / doc["embeddings"], folder / "emb.npy")
    doc["embeddings"] = "emb.npy"
    (folder / "vocabulary.json").write_text(json.dumps(doc))
    return folder / "vocabulary.json"


@pytest.mark.slow
def test_cli_run_takes_a_vocabulary_file(
    tiny_bundle: Path, tiny_run: tuple[Path, object, list], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The CLI's user owns the disk: ``--vocabulary FILE`` is read by the CLI, and the run labels with it."""
    vocabulary = _renamed_vocabulary(tiny_bundle, tmp_path / "mine")
    out = tmp_path / "cli-vocabulary"
    shutil.copytree(tiny_run[0] / "stages", out / "stages")  # the label set changes only the labeling stage
    assert (
        cli_main(["run", str(tiny_bundle), "--out", str(out), "-q", *TINY_RUN_FIT, "--vocabulary", str(vocabulary)])
        == 0
    )
    capsys.readouterr()
    names = [c["name"] for c in json.loads((out / "vocabulary.json").read_text())["classes"]]
    assert names == [c["name"] for c in json.loads(vocabulary.read_text())["classes"]]
    instances = json.loads((out / "instances.json").read_text())
    assert instances
    assert {i["class_name"] for i in instances} <= set(names)
    assert json.loads((out / "report.json").read_text())["vocabulary"] == "inline"
    assert cli_main(["run", str(tiny_bundle), "--out", str(out), "-q", "--vocabulary", str(tmp_path / "no.json")]) == 2
    assert "no such file" in capsys.readouterr().err


def test_run_pipeline_takes_names_not_paths(tiny_bundle: Path, tmp_path: Path) -> None:
    """The library (the service's worker path) resolves built-in names only: a path, even of a real
    vocabulary.json, is refused before the first stage after validate, and the message does not repeat it."""
    vocabulary = _renamed_vocabulary(tiny_bundle, tmp_path / "mine")
    with pytest.raises(InputError, match="unknown built-in label set") as caught:
        run_pipeline(tiny_bundle, tmp_path / "out", vocabulary=str(vocabulary))
    assert str(vocabulary) not in str(caught.value)
    assert not (tmp_path / "out" / "labels.npz").exists()


def _copy_checkpoints(run: Path, to: Path) -> None:
    shutil.copytree(run / "stages", to / "stages")


SHORT_FIT = PipelineConfig().with_overrides({"appearance": {"iterations": 2}})


@pytest.mark.slow  # reads tiny_run, a whole pipeline run
def test_the_results_are_written_before_the_fit_and_gaussians_ply_is_replaced_after(
    tiny_bundle: Path, tiny_run: tuple[Path, object, list], tmp_path: Path
) -> None:
    out, first, _ = tiny_run
    _copy_checkpoints(out, tmp_path)
    seen: list[str] = []
    at_results: dict[str, object] = {}

    def on_results(result: object) -> None:
        at_results["report"] = json.loads((tmp_path / "report.json").read_text())
        at_results["files"] = {p.name for p in tmp_path.iterdir()}
        at_results["stages_seen"] = list(dict.fromkeys(seen))
        at_results["result"] = result
        at_results["gaussians"] = read_ply_vertices(tmp_path / "gaussians.ply")
        assert load_result(tmp_path).instances  # queries work from here on

    result = run_pipeline(
        tiny_bundle, tmp_path, SHORT_FIT, on_progress=lambda s, d, t: seen.append(s), on_results=on_results
    )
    assert "appearance" not in at_results["stages_seen"], "the fit starts after the results"
    assert at_results["stages_seen"][-1] == "export"
    assert {"labels.npz", "instances.json", "panoptic.ply", "gaussians.ply", "report.json"} <= at_results["files"]
    assert at_results["report"]["appearance"] == {"state": "running"}
    assert at_results["result"].instances == first.instances == result.instances
    initial = at_results["gaussians"]
    assert np.all(initial["opacity"] == 0.0), "the initialisation's logit opacity"
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["appearance"]["state"] == "succeeded" == result.fit_state
    assert report["appearance"]["iterations"] == 2
    assert [s["stage"] for s in report["stages"]] == list(STAGES)
    fitted = read_ply_vertices(tmp_path / "gaussians.ply")
    assert not np.array_equal(fitted["opacity"], initial["opacity"])
    assert np.array_equal(fitted["semantic"], initial["semantic"])
    assert not list(tmp_path.glob(".*tmp")), "no temporary file is left"


@pytest.mark.slow  # reads tiny_run, a whole pipeline run
def test_a_fit_that_fails_leaves_the_results_and_says_so(
    tiny_bundle: Path, tiny_run: tuple[Path, object, list], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from panogs_core.errors import NumericalError
    from panogs_core.pipeline import stage_table

    out, first, _ = tiny_run
    _copy_checkpoints(out, tmp_path)

    def broken_fit(*args: object, **kwargs: object) -> None:
        raise NumericalError("the loss is NaN at iteration 1")

    monkeypatch.setattr(stage_table, "fit_appearance", broken_fit)  # what the table's appearance entry calls
    result = run_pipeline(tiny_bundle, tmp_path, SHORT_FIT)
    assert result.fit_state == "failed"
    assert result.instances == first.instances
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["appearance"] == {"state": "failed", "error": "NumericalError: the loss is NaN at iteration 1"}
    assert load_result(tmp_path).instances
    assert np.all(read_ply_vertices(tmp_path / "gaussians.ply")["opacity"] == 0.0), "the initialisation stays"


@pytest.mark.slow  # reads tiny_run, a whole pipeline run
def test_a_fit_cancelled_after_the_results_leaves_them_and_says_so(
    tiny_bundle: Path, tiny_run: tuple[Path, object, list], tmp_path: Path
) -> None:
    out, first, _ = tiny_run
    _copy_checkpoints(out, tmp_path)

    def stop_in_the_fit(stage: str, done: int, total: int) -> None:
        if stage == "appearance" and done == 1:
            raise Cancelled("canceled at the owner's request")

    with pytest.raises(Cancelled):
        run_pipeline(tiny_bundle, tmp_path, SHORT_FIT, on_progress=stop_in_the_fit)
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["appearance"] == {"state": "canceled", "error": "Cancelled: canceled at the owner's request"}
    assert [i.to_json()["id"] for i in load_result(tmp_path).instances] == [i["id"] for i in first.instances]
    resumed = run_pipeline(tiny_bundle, tmp_path, SHORT_FIT)  # a re-run finishes the fit from the checkpoints
    assert resumed.fit_state == "succeeded"
    assert {t.name for t in resumed.timings if not t.cached} <= {"validate", "maps_2d", "export", "appearance"}


@pytest.mark.slow  # reads tiny_run, a whole pipeline run
def test_the_cli_prints_the_results_before_the_fit(
    tiny_bundle: Path, tiny_run: tuple[Path, object, list], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import panogs_core.cli.commands.run as run_command

    out = tmp_path / "cli-run"
    _copy_checkpoints(tiny_run[0], out)
    before_fit: list[str] = []

    class Recorder:
        """Takes what was printed when the fit reports its first progress."""

        def __call__(self, stage: str, done: int, total: int) -> None:
            if stage == "appearance" and not before_fit:
                before_fit.append(capsys.readouterr().out)

        def close(self) -> None:
            return None

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(run_command, "stage_reporter", lambda quiet, stream: Recorder())
        assert cli_main(["run", str(tiny_bundle), "--out", str(out), "--set", "appearance.iterations=2"]) == 0
    after = capsys.readouterr().out
    assert len(before_fit) == 1
    assert "instances" in before_fit[0]
    assert "mIoU" in before_fit[0]
    assert "fitting the Gaussian scene" in before_fit[0]
    assert "gaussians: PSNR" not in before_fit[0]
    assert "gaussians: PSNR" in after


@pytest.mark.slow  # reads tiny_run, a whole pipeline run
def test_a_checkpoint_that_cannot_be_written_fails_the_run_and_names_no_file(
    tiny_bundle: Path, tiny_run: tuple[Path, object, list], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Checkpoints are written by a thread beside the next stages: its error must still end the run, and the
    manifest must name no file but the one made with its key (a resumed run reads what the key names)."""
    from panogs_core.stages.clustering import Clusters

    out, _, _ = tiny_run
    _copy_checkpoints(out, tmp_path)
    before = json.loads((tmp_path / "stages" / "manifest.json").read_text())
    old_clusters = (tmp_path / "stages" / "clustering.npz").read_bytes()
    cfg = SHORT_FIT.with_overrides({"clustering": {"thresholds": [0.9, 0.7, 0.5]}})  # clustering computed again

    def full_disk(self: object, path: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Clusters, "save", full_disk)
    with pytest.raises(OSError, match="No space left"):
        run_pipeline(tiny_bundle, tmp_path, cfg)
    manifest = json.loads((tmp_path / "stages" / "manifest.json").read_text())
    assert manifest.get("clustering") in (None, before["clustering"])
    assert (tmp_path / "stages" / "clustering.npz").read_bytes() == old_clusters, "the old key's file is intact"
    assert {s: manifest[s] for s in ("fusion", "superprimitives")} == {
        s: before[s] for s in ("fusion", "superprimitives")
    }, "the stages before keep theirs"
    assert "labeling" not in manifest or manifest["labeling"] == before["labeling"], "no stage after it was recorded"


class MemoryCheckpoints:
    """A shared checkpoint store in memory (the service keeps one per scene in its storage)."""

    def __init__(self) -> None:
        self.files: dict[tuple[str, str], bytes] = {}
        self.input_hash: str | None = None

    def fetch(self, stage: str, key: str, dest: Path) -> bool:
        if (stage, key) not in self.files:
            return False
        dest.write_bytes(self.files[stage, key])
        return True

    def store(self, stage: str, key: str, path: Path) -> None:
        self.files[stage, key] = path.read_bytes()

    def known_input_hash(self) -> str | None:
        return self.input_hash

    def keep_input_hash(self, sha256: str) -> None:
        self.input_hash = sha256


@pytest.mark.slow  # two pipeline runs
def test_a_later_run_of_the_same_bundle_takes_its_hash_from_the_shared_store(
    tiny_bundle: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Hashing the bundle is most of a re-run's time at ScanNet size: the first run keeps the hash with the shared
    checkpoints, a later run of the same bundle finds its stage keys from it without reading the bundle's files."""
    from panogs_core.io.bundle import open_bundle
    from panogs_core.pipeline import checkpoints
    from panogs_core.pipeline.input_hash import hash_bundle

    shared = MemoryCheckpoints()
    first = run_pipeline(tiny_bundle, tmp_path / "first", SHORT_FIT, shared=shared)
    report = json.loads((tmp_path / "first" / "report.json").read_text())
    assert shared.input_hash == report["input_sha256"] == hash_bundle(open_bundle(tiny_bundle))

    def no_hashing(_: object) -> str:
        raise AssertionError("the bundle was hashed again")

    monkeypatch.setattr(checkpoints, "hash_bundle", no_hashing)
    again = run_pipeline(tiny_bundle, tmp_path / "again", SHORT_FIT, shared=shared)
    assert all(t.cached for t in again.timings if t.name not in ("validate", "maps_2d", "export"))
    assert again.instances == first.instances
    assert json.loads((tmp_path / "again" / "report.json").read_text())["input_sha256"] == shared.input_hash


def test_the_stage_table_names_only_values_written_before_they_are_read() -> None:
    """The run reads its stages, their order and their calls from the table: each value a stage reads is a run
    argument or the value of an entry before it, the names are unique, and ``STAGES`` is the table's timed entries."""
    from panogs_core.pipeline import stage_table as st

    written = set(st.RUN_ARGUMENTS)
    for spec in st.PIPELINE:
        missing = [name for name in spec.reads if name not in written]
        assert not missing, f"{spec.name} reads {missing} before any entry writes it"
        written.add(spec.output)
    assert len(st.BY_NAME) == len(st.PIPELINE)
    assert STAGES == tuple(spec.name for spec in st.PIPELINE if spec.timed)
    assert STAGES[0] == "validate"
    assert STAGES[-1] == "appearance"
    assert [spec.name for spec in st.PIPELINE if spec.after_results] == ["appearance"]


@pytest.mark.slow  # reads tiny_run, a whole pipeline run
def test_a_stage_added_to_the_table_runs_in_its_place_and_is_reported(
    tiny_bundle: Path, tiny_run: tuple[Path, object, list], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """One entry adds a stage: here one that hands the bundle on, placed before the first stage that reads maps;
    the run calls it there, reports it, and the results are the same."""
    from panogs_core.io.bundle import Bundle
    from panogs_core.pipeline import stage_table as st

    out, first, _ = tiny_run
    _copy_checkpoints(out, tmp_path)
    called: list[str] = []

    def hand_on(bundle: Bundle, cfg: PipelineConfig, progress: object) -> Bundle:
        called.append(bundle.name)
        return bundle

    entry = st.StageSpec("added", hand_on, ("bundle",), writes="bundle")
    at = [spec.name for spec in st.PIPELINE].index("fusion")
    monkeypatch.setattr(st, "PIPELINE", (*st.PIPELINE[:at], entry, *st.PIPELINE[at:]))
    seen: list[str] = []
    result = run_pipeline(tiny_bundle, tmp_path, SHORT_FIT, on_progress=lambda s, d, t: seen.append(s))
    assert called == [first.scene_name]
    report = json.loads((tmp_path / "report.json").read_text())
    names = [s["stage"] for s in report["stages"]]
    assert names == [*STAGES[: STAGES.index("fusion")], "added", *STAGES[STAGES.index("fusion") :]]
    assert "added" in seen
    assert result.instances == first.instances
    for name in ("labels.npz", "instances.json", "panoptic.ply"):
        assert (tmp_path / name).read_bytes() == (out / name).read_bytes()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="a thread's niceness is its own on Linux only")
def test_bundle_hash_thread_runs_at_a_lower_priority(monkeypatch: pytest.MonkeyPatch) -> None:
    """The bundle's hash yields the cores to the stages' threads; the caller's own priority is untouched."""
    import os
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from panogs_core.pipeline import checkpoints

    def niceness(_: object) -> str:
        return str(os.getpriority(os.PRIO_PROCESS, threading.get_native_id()))

    monkeypatch.setattr(checkpoints, "hash_bundle", niceness)
    before = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    with ThreadPoolExecutor(max_workers=1) as pool:
        inside = int(pool.submit(checkpoints._hash_at_low_priority, None).result())
    assert inside == min(19, before + checkpoints._HASH_NICENESS)
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == before


@pytest.mark.slow  # a pipeline run, and one resumed from tiny_run's checkpoints
def test_the_bundle_is_hashed_after_fusion_unless_a_checkpoint_may_be_read_back(
    tiny_bundle: Path, tiny_run: tuple[Path, object, list], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The hash would take a core the frame stages decode on: a run with nothing to read back starts it once
    fusion is done; a resumed run needs its keys from the first stage on and starts it at once. Both report it."""
    from panogs_core.io.bundle import open_bundle
    from panogs_core.pipeline import checkpoints

    events: list[str] = []
    real_hash = checkpoints.hash_bundle

    def recorded(scene: object) -> str:
        events.append("hash")
        return real_hash(scene)  # type: ignore[arg-type]

    def progress(stage: str, done: int, total: int) -> None:
        if not events or events[-1] != stage:
            events.append(stage)

    monkeypatch.setattr(checkpoints, "hash_bundle", recorded)
    run_pipeline(tiny_bundle, tmp_path / "fresh", TINY_RUN_CONFIG, on_progress=progress)
    assert events.count("hash") == 1
    assert events.index("hash") > len(events) - 1 - events[::-1].index("fusion"), events
    report = json.loads((tmp_path / "fresh" / "report.json").read_text())
    assert report["input_sha256"] == real_hash(open_bundle(tiny_bundle))

    events.clear()
    out, first, _ = tiny_run
    _copy_checkpoints(out, tmp_path / "resumed")
    again = run_pipeline(tiny_bundle, tmp_path / "resumed", TINY_RUN_CONFIG, on_progress=progress)
    assert next(t for t in again.timings if t.name == "primitives").cached
    assert events.index("hash") < events.index("visibility"), events  # the cached primitives waited for their key
    assert again.instances == first.instances


@pytest.mark.slow  # a pipeline run
def test_the_results_do_not_wait_for_the_bundles_hash(
    tiny_bundle: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """On a busy machine the low-priority hash can lag far behind the stages: the results (their files, their
    report, ``on_results``) come without it, and the run's last report and the checkpoints' manifest have it."""
    import threading

    from panogs_core.io.bundle import open_bundle
    from panogs_core.pipeline import checkpoints

    release = threading.Event()
    real_hash = checkpoints.hash_bundle

    def lagging(scene: object) -> str:
        assert release.wait(timeout=120), "the results never came"
        return real_hash(scene)  # type: ignore[arg-type]

    at_results: dict[str, object] = {}

    def on_results(result: object) -> None:
        at_results.update(json.loads((tmp_path / "report.json").read_text()))
        at_results["labels"] = (tmp_path / "labels.npz").exists()
        release.set()  # the hash ends only once the results are out: waiting for it first would time out

    monkeypatch.setattr(checkpoints, "hash_bundle", lagging)
    run_pipeline(tiny_bundle, tmp_path, TINY_RUN_CONFIG, on_results=on_results)
    assert at_results["labels"]
    assert at_results["input_sha256"] is None
    assert 0 < at_results["results_wall_s"] <= at_results["total_wall_s"]  # type: ignore[operator]
    final = json.loads((tmp_path / "report.json").read_text())
    assert final["input_sha256"] == real_hash(open_bundle(tiny_bundle))
    assert final["results_wall_s"] == at_results["results_wall_s"]
    manifest = json.loads((tmp_path / "stages" / "manifest.json").read_text())
    assert {"primitives", "fusion", "labeling"} <= set(manifest)  # recorded once the hash was known


@pytest.mark.slow  # reads tiny_run, a whole pipeline run, and runs the stages after fusion again
def test_the_stages_that_need_no_field_run_beside_its_fit(
    tiny_bundle: Path, tiny_run: tuple[Path, object, list], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The mask look-ups and the kNN graph read nothing of the field: they run on a thread of their own while it
    fits (the fit here waits until the kNN graph has started: one after the other, it would time out). Their
    progress still comes at their places in the table, their rows say what they ran beside, the results are the
    same."""
    import threading
    import time

    from panogs_core.pipeline import run as run_module
    from panogs_core.pipeline import stage_table as st

    monkeypatch.setattr(run_module, "decode_threads", lambda: 2)  # two cores' worth, whatever the test's share

    out, first, _ = tiny_run
    _copy_checkpoints(out, tmp_path)
    for stage in STAGES[STAGES.index("language_field") :]:
        (tmp_path / "stages" / f"{stage}.npz").unlink(missing_ok=True)
    threads: dict[str, str] = {}
    knn_started = threading.Event()
    real_masks, real_knn, real_fit = st.observe_masks, st.build_knn, st.set_up_language_field

    def masks(*args: object, **kwargs: object) -> object:
        threads["masks"] = threading.current_thread().name
        return real_masks(*args, **kwargs)  # type: ignore[arg-type]

    def knn(*args: object, **kwargs: object) -> object:
        threads["neighbors"] = threading.current_thread().name
        knn_started.set()
        time.sleep(1.0)  # still running when the run reaches its place: taken there once it is made
        return real_knn(*args, **kwargs)  # type: ignore[arg-type]

    def fit_once_started(*args: object, **kwargs: object) -> object:
        assert knn_started.wait(timeout=60), "the kNN graph did not start beside the fit"
        return real_fit(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(st, "observe_masks", masks)
    monkeypatch.setattr(st, "build_knn", knn)
    monkeypatch.setattr(st, "set_up_language_field", fit_once_started)
    events: list[str] = []

    def progress(stage: str, done: int, total: int) -> None:
        if stage not in events:
            events.append(stage)

    result = run_pipeline(tiny_bundle, tmp_path, TINY_RUN_CONFIG, on_progress=progress)
    assert threads == {"masks": "beside-language_field", "neighbors": "beside-language_field"}
    assert events[events.index("language_field") :][:4] == ["language_field", "masks", "neighbors", "superprimitives"]
    rows = json.loads((tmp_path / "report.json").read_text())["stages"]
    assert [r["stage"] for r in rows] == [s for s in STAGES if s in {r["stage"] for r in rows}]  # the table's order
    assert {r["stage"]: r.get("beside") for r in rows if "beside" in r} == {
        "masks": "language_field",
        "neighbors": "language_field",
    }
    assert result.instances == first.instances


@pytest.mark.slow  # a pipeline run
def test_the_background_work_takes_turns_on_one_lane(
    tiny_bundle: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The stages beside the field, the checkpoint writes and the bundle's hash each hold the run's background lane
    while they work (so at most one of them wants a core beside the fit), and a stage beside runs on one thread."""
    import hashlib
    import threading
    from types import SimpleNamespace

    from panogs_core.pipeline import input_hash, lane
    from panogs_core.pipeline import run as run_module
    from panogs_core.pipeline import stage_table as st
    from panogs_core.stages.fusion import FusedFeatures
    from panogs_core.threads import decode_threads, query_workers

    class RecordingLock:
        """The lane's lock, knowing which thread holds it."""

        def __init__(self) -> None:
            self._lock, self.holder = threading.Lock(), None

        def acquire(self) -> None:
            self._lock.acquire()
            self.holder = threading.get_ident()

        def release(self) -> None:
            self.holder = None
            self._lock.release()

    lock = RecordingLock()
    monkeypatch.setattr(lane, "_LANE", lock)
    monkeypatch.setattr(run_module, "decode_threads", lambda: 2)  # two cores' worth, whatever the test's share
    seen: dict[str, list[tuple[bool, ...]]] = {"beside": [], "write": [], "hash": []}

    def mine() -> bool:
        return lock.holder == threading.get_ident()

    real_masks, real_knn, real_save = st.observe_masks, st.build_knn, FusedFeatures.save

    def masks(*args: object, **kwargs: object) -> object:
        seen["beside"].append((mine(), decode_threads() == 1))
        return real_masks(*args, **kwargs)  # type: ignore[arg-type]

    def knn(*args: object, **kwargs: object) -> object:
        seen["beside"].append((mine(), query_workers() == 1))
        return real_knn(*args, **kwargs)  # type: ignore[arg-type]

    def save(self: FusedFeatures, path: object) -> None:
        seen["write"].append((mine(),))
        real_save(self, path)  # type: ignore[arg-type]

    class Digest:
        def __init__(self) -> None:
            self._digest = hashlib.new("sha256")

        def update(self, chunk: bytes) -> None:
            seen["hash"].append((mine(),))
            self._digest.update(chunk)

        def hexdigest(self) -> str:
            return self._digest.hexdigest()

    monkeypatch.setattr(st, "observe_masks", masks)
    monkeypatch.setattr(st, "build_knn", knn)
    monkeypatch.setattr(FusedFeatures, "save", save)
    monkeypatch.setattr(input_hash, "hashlib", SimpleNamespace(sha256=Digest))  # the bundle's hash only
    run_pipeline(tiny_bundle, tmp_path, TINY_RUN_CONFIG, resume=False)
    assert seen["beside"] == [(True, True), (True, True)]
    assert seen["write"] == [(True,)]
    assert seen["hash"]
    assert all(held for (held,) in seen["hash"])
    assert lock.holder is None


@pytest.mark.slow  # a pipeline run
def test_a_process_given_one_thread_runs_nothing_beside_the_field(
    tiny_bundle: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``--threads 1`` (or a tile's one-core share): the stages run one after the other, on the run's thread."""
    import threading

    from panogs_core.pipeline import run as run_module
    from panogs_core.pipeline import stage_table as st

    monkeypatch.setattr(run_module, "decode_threads", lambda: 1)
    threads: list[str] = []
    real_knn = st.build_knn

    def knn(*args: object, **kwargs: object) -> object:
        threads.append(threading.current_thread().name)
        return real_knn(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(st, "build_knn", knn)
    run_pipeline(tiny_bundle, tmp_path, TINY_RUN_CONFIG)
    assert threads == [threading.current_thread().name]
    rows = json.loads((tmp_path / "report.json").read_text())["stages"]
    assert not [r for r in rows if "beside" in r]


@pytest.mark.slow  # a pipeline run
@pytest.mark.parametrize("threads", [2, 1])
def test_the_fused_features_are_freed_before_the_field_decodes(
    tiny_bundle: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, threads: int
) -> None:
    """The field takes the fused features: once its training set is built and the stages beside it have their
    cosines and colours, nothing holds them, so the decoding's (N, D) output is never made beside them. On one
    thread (nothing beside) the class cosines come after the field: the run keeps them for that."""
    import time
    import weakref

    from panogs_core.pipeline import run as run_module
    from panogs_core.pipeline import stage_table as st
    from panogs_core.stages.language_field import triplane

    monkeypatch.setattr(run_module, "decode_threads", lambda: threads)
    fused_ref: list[weakref.ref[np.ndarray]] = []
    alive_at_decode: list[bool] = []
    real_fusion, real_decode = st.fuse_features, triplane.decode_features

    def fusion(*args: object, **kwargs: object) -> object:
        fused = real_fusion(*args, **kwargs)  # type: ignore[arg-type]
        fused_ref.append(weakref.ref(fused.features))
        return fused

    def decode(*args: object, **kwargs: object) -> object:
        deadline = time.monotonic() + 30  # the thread beside may still be making the cosines (a loaded host)
        while fused_ref[0]() is not None and time.monotonic() < deadline and threads > 1:
            time.sleep(0.01)
        alive_at_decode.append(fused_ref[0]() is not None)
        return real_decode(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(st, "fuse_features", fusion)
    monkeypatch.setattr(triplane, "decode_features", decode)
    result = run_pipeline(tiny_bundle, tmp_path, TINY_RUN_CONFIG)
    assert alive_at_decode == [threads == 1]
    assert result.instances


@pytest.mark.slow  # a pipeline run up to the field
def test_an_error_of_a_stage_beside_the_field_is_raised_at_its_place(
    tiny_bundle: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from panogs_core.pipeline import run as run_module
    from panogs_core.pipeline import stage_table as st

    monkeypatch.setattr(run_module, "decode_threads", lambda: 2)  # two cores' worth, whatever the test's share

    def broken(*args: object, **kwargs: object) -> object:
        raise ValueError("the mask look-ups failed")

    monkeypatch.setattr(st, "observe_masks", broken)
    seen: list[str] = []
    with pytest.raises(ValueError, match="mask look-ups failed"):
        run_pipeline(tiny_bundle, tmp_path, TINY_RUN_CONFIG, on_progress=lambda s, d, t: seen.append(s))
    assert "language_field" in seen  # the field ran to its end: the error waited for the masks' place
    assert "masks" not in seen
    assert "superprimitives" not in seen
    assert not (tmp_path / "labels.npz").exists()


@pytest.mark.slow  # a pipeline run up to the field
def test_a_run_stopped_in_the_field_waits_for_the_stages_beside_it(
    tiny_bundle: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A stop during the fit ends the run only once the stages beside it are done: none is left writing into the
    run folder after ``run_pipeline`` has raised."""
    import threading
    import time

    from panogs_core.pipeline import run as run_module
    from panogs_core.pipeline import stage_table as st

    monkeypatch.setattr(run_module, "decode_threads", lambda: 2)  # two cores' worth, whatever the test's share

    real_knn = st.build_knn

    def slow_knn(*args: object, **kwargs: object) -> object:
        time.sleep(1.0)
        return real_knn(*args, **kwargs)  # type: ignore[arg-type]

    def stop_in_the_field(stage: str, done: int, total: int) -> None:
        if stage == "language_field":
            raise Cancelled("stopped")

    monkeypatch.setattr(st, "build_knn", slow_knn)
    with pytest.raises(Cancelled):
        run_pipeline(tiny_bundle, tmp_path, TINY_RUN_CONFIG, on_progress=stop_in_the_field)
    assert not [t.name for t in threading.enumerate() if t.name.startswith("beside-")]
    assert (tmp_path / "stages" / "neighbors.npz").exists()  # finished, and its checkpoint written before the stop


@pytest.mark.slow
def test_run_as_the_process_entry_ends_after_its_exit_handlers(tiny_bundle: Path, tmp_path: Path) -> None:
    """``main()`` with no argv ends a successful ``run`` without the interpreter's teardown: the exit handlers
    have run, the output streams are flushed and the run folder is complete (what resume reads included)."""
    import subprocess

    marker = tmp_path / "handlers-ran"
    code = (
        "import atexit, pathlib, sys; from panogs_core.cli import main; "
        f"atexit.register(pathlib.Path({str(marker)!r}).write_text, 'yes'); main(); print('returned')"
    )
    out = tmp_path / "run"
    args = [sys.executable, "-c", code, "run", str(tiny_bundle), "--out", str(out), "--set", "appearance.enabled=false"]
    root = str(Path(__file__).resolve().parents[2])
    done = subprocess.run(args, capture_output=True, text=True, cwd=root, check=False)
    assert done.returncode == 0, done.stderr
    assert "returned" not in done.stdout  # ended inside main
    assert "the results are written" in done.stdout  # flushed
    assert marker.read_text() == "yes"
    assert (out / "report.json").is_file()
    assert (out / "stages" / "manifest.json").is_file()
