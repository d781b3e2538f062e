"""Releases: v1 from a curated run, v2 after a clip was added reuses v1's shards by
content and lists exactly the new pairs; both load with ``webdataset`` and ``datasets``."""

from __future__ import annotations

import hashlib
import json
import shutil

import pytest

from handedit.flows.cli import main
from handedit.flows.config import ClusterConfig, CurateConfig
from handedit.flows.curate import run_curate
from handedit.sources.synthetic import make_clip_specs
from handedit.storage import Location
from handedit.storage.releases import read_pairs, read_release, shard_urls, versions
from handedit.storage.summary import read_index

W, H, T, F = 96, 72, 16, 8
SHARD_MB = "0.5"  # ~16 frames of 96x72 pairs: one clip per shard here


def curate(out, n: int, cluster) -> None:
    summary = run_curate(CurateConfig(out=str(out), clips=make_clip_specs(n, seed=11, n_frames=T, width=W, height=H),
                                      embodiments=["allegro"], frames_per_chunk=F, shard_size=1,
                                      cluster=ClusterConfig(address=cluster.scheduler_address)))
    assert not summary["errors"]


def kept(run) -> int:
    return int(read_index(Location(run))["kept"].sum())


def sha256(path) -> str:
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


@pytest.fixture(scope="module")
def released(tmp_path_factory, prefect_api, dask_cluster):
    tmp = tmp_path_factory.mktemp("release")
    run, rel = tmp / "run", tmp / "releases"
    curate(run, 2, dask_cluster)
    argv = ["release", "--from", str(run), "--out", str(rel), "--shard-mb", SHARD_MB,
            "--address", dask_cluster.scheduler_address]
    assert main(argv) == 0
    v1 = {f.name: sha256(f) for f in (rel / "shards").glob("*.tar")}
    n1 = kept(run)
    curate(run, 3, dask_cluster)  # one clip more: a new curate shard
    assert main(argv) == 0
    return {"run": run, "rel": rel, "v1_files": v1, "n1": n1, "tmp": tmp, "cluster": dask_cluster}


def test_v1_holds_every_kept_pair_with_hashed_shards(released):
    loc = Location(released["rel"])
    m = read_release(loc, "v0001")
    assert m["version"] == "v0001" and m["parent"] is None
    assert m["counts"]["pairs"] == released["n1"] > 0 and m["counts"]["shards"] == 2 == len(released["v1_files"])
    for s in m["shards"]:
        assert sha256(released["rel"] / s["path"]) == s["sha256"] and not s["reused"]
    stages = m["sources"][0]["stages"]
    assert stages["harmonize"]["version"] is not None and "code_version" in m and m["sources"][0]["fingerprint"]
    sheet = json.loads((released["rel"] / "v0001" / "datasheet.json").read_text())
    assert sheet["pairs"] == released["n1"] and sheet["counts"]["embodiment"] == {"allegro": released["n1"]}
    md = (released["rel"] / "v0001" / "datasheet.md").read_text()
    assert "Rejections by primary cause" in md and "| Primary failure cause |" in md


def test_v2_reuses_unchanged_shards_and_lists_exactly_the_new_pairs(released):
    loc = Location(released["rel"])
    assert versions(loc) == ["v0001", "v0002"]
    m1, m2 = read_release(loc, "v0001"), read_release(loc, "v0002")
    assert m2["parent"] == "v0001" and m2["counts"]["shards"] == 3 and m2["counts"]["shards_reused"] == 2
    assert {s["sha256"] for s in m1["shards"]} < {s["sha256"] for s in m2["shards"]}
    for name, digest in released["v1_files"].items():  # v1's files untouched
        assert sha256(released["rel"] / "shards" / name) == digest
    log = json.loads((released["rel"] / "v0002" / "changelog.json").read_text())
    new = read_pairs(loc, "v0002")
    assert log["removed"] == [] and log["changed"] == []
    assert sorted(log["added"]) == sorted(new.loc[new["clip"] == "synthetic-0002", "id"]) and log["added"]
    assert len(new) == kept(released["run"])


def test_the_scheduled_release_publishes_nothing_when_nothing_changed(released):
    """``publish_unchanged=False`` (what ``nightly`` runs): the same pairs in the same shards as
    the latest version publish no version, and say so (in the log and the returned note)."""
    from handedit.flows.release import ReleaseConfig, run_release

    cfg = ReleaseConfig(sources=[str(released["run"])], out=str(released["rel"]), target_shard_bytes=int(float(SHARD_MB) * (1 << 20)),
                        cluster=ClusterConfig(address=released["cluster"].scheduler_address), publish_unchanged=False)
    m = run_release(cfg)
    assert m["published"] is False and m["version"] == "v0002" and m["note"].startswith("nothing changed since v0002")
    assert versions(Location(released["rel"])) == ["v0001", "v0002"]


def test_both_releases_load_with_webdataset_and_datasets(released, monkeypatch):
    import datasets
    import webdataset as wds

    loc = Location(released["rel"])
    for version in ("v0001", "v0002"):
        urls = shard_urls(loc, version)
        n = read_release(loc, version)["counts"]["pairs"]
        samples = list(wds.WebDataset(urls, shardshuffle=False, empty_check=False))
        assert len(samples) == n
        s = samples[0]
        assert {"src.png", "gt.png", "composite.png", "human_mask.png", "robot_mask.png", "object_mask.png", "json"} <= set(s)
        meta = json.loads(s["json"])
        assert meta["embodiment"] == "allegro" and meta["instruction"].startswith("Replace the human hand region")
        monkeypatch.setenv("HF_DATASETS_OFFLINE", "1")
        monkeypatch.setenv("HF_HUB_OFFLINE", "1")
        ds = datasets.load_dataset("webdataset", data_files={"train": urls}, split="train",
                                   cache_dir=str(released["tmp"] / f"hf-{version}"))
        assert len(ds) == n and ds[0]["gt.png"].size == (W, H)


def test_a_release_with_a_hole_publishes_nothing(released, capsys):
    run = released["tmp"] / "holed"
    shutil.copytree(released["run"], run)
    image = next((run / "handedit.zarr" / "clips" / "synthetic-0000" / "embodiments" / "allegro" / "harmonize" / "image"
                  / "c").rglob("*"))
    while image.is_dir():
        image = next(image.iterdir())
    image.unlink()
    rel = released["tmp"] / "releases-holed"
    argv = ["release", "--from", str(run), "--out", str(rel), "--address", released["cluster"].scheduler_address]
    assert main(argv) == 2
    assert "missing" in capsys.readouterr().err
    assert versions(Location(rel)) == []


def test_bench_build_from_a_release_equals_the_store_build(released, capsys):
    from handedit.storage.benchmark import read_image

    a, b = released["tmp"] / "bench-store", released["tmp"] / "bench-release"
    assert main(["bench", "build", "--store", str(released["run"]), "--out", str(a), "-n", "4"]) == 0
    assert main(["bench", "build", "--release", str(released["rel"] / "v0002"), "--out", str(b), "-n", "4"]) == 0
    ma, mb = (json.loads((d / "testset.json").read_text())["items"] for d in (a, b))
    assert [i["id"] for i in ma] == [i["id"] for i in mb] and len(ma) >= 4
    for item in ma:
        for f in ("src.png", "gt.png", "human_mask.png", "robot_mask.png"):
            fa = next(p for p in a.rglob(f) if item["id"] in str(p))
            fb = next(p for p in b.rglob(f) if item["id"] in str(p))
            assert (read_image(fa) == read_image(fb)).all(), (item["id"], f)


def test_release_qa_page_renders_in_headless_chromium(released):
    """The page in a real browser: every image decodes, the counts and the breakdown table are there."""
    import re

    from _browser import dom, screenshot

    page = released["rel"] / "v0002" / "qa.html"
    assert main(["dashboard", "--release", str(released["rel"] / "v0002")]) == 0 and page.is_file()
    text = dom(page.as_uri())
    check = re.search(r'id="qa-check" data-images="(\d+)" data-broken="(\d+)"', text)
    assert check, text[-2000:]
    n_images, broken = map(int, check.groups())
    m = read_release(Location(released["rel"]), "v0002")
    assert broken == 0 and n_images >= 3
    assert f'data-pairs="{m["counts"]["pairs"]}"' in text and "Rejections by primary cause" in text
    screenshot(page.as_uri(), released["tmp"] / "qa_release.png", wait_s=2.0, size=(1280, 2400))


def test_datasheet_families_follow_the_pipeline_order():
    from handedit.release.datasheet import FAMILY
    from handedit.storage.layout import stage_names

    assert tuple(FAMILY) == stage_names()  # the primary cause is the earliest stage in this order


def test_a_release_run_publishes_its_artifact(released):
    """The release in Prefect's UI: version, counts and where its datasheet and changelog are."""
    import asyncio

    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterKey

    async def latest():
        async with get_client() as client:
            return await client.read_artifacts(artifact_filter=ArtifactFilter(key=ArtifactFilterKey(any_=["release"])))

    arts = asyncio.run(latest())
    texts = [str(a.data) for a in arts]
    assert any("# release v0002 (parent v0001)" in t and "datasheet.md" in t and "changelog.md" in t for t in texts), texts


def test_a_hostile_manifest_renders_inert_in_headless_chromium(released):
    """Manifest fields and links are data: markup in them is shown as text, scripts never run."""
    import json as js
    import shutil as sh

    from _browser import dom

    rel = released["tmp"] / "hostile"
    sh.copytree(released["rel"], rel)
    path = rel / "v0001" / "manifest.json"
    m = js.loads(path.read_text())
    bad = "<img src=x onerror=\"document.title='pwned'\">"
    m["counts"]["pairs"] = f'1" onmouseover="x" data-x="{bad}'
    m["counts"]["shards_reused"] = "<script>document.title='pwned'</script>"
    m["code_version"] = bad
    m["links"] = {"Prefect run": "javascript:document.title='pwned'", "Dask dashboard": "http://127.0.0.1:8787/status"}
    path.write_text(js.dumps(m))
    assert main(["dashboard", "--release", str(rel / "v0001")]) == 0
    page = rel / "v0001" / "qa.html"
    text = page.read_text()
    assert 'href="javascript' not in text and 'href="http://127.0.0.1:8787/status"' in text
    assert "<script>document" not in text
    shown = dom(page.as_uri(), budget_ms=5000)
    assert "<title>handedit release v0001</title>" in shown and "pwned" not in shown.split("</title>")[0]
    assert "<img src=\"x\"" not in shown and "&lt;img src=x" in shown  # shown, not made


def test_clip_ids_that_differ_only_by_a_dot_keep_distinct_sample_keys():
    from handedit.release.samples import sample_key
    from handedit.storage.layout import safe_name

    keys = {sample_key(c, "allegro", 3) for c in ("take.1", "take_1", "take-1")}
    assert len(keys) == 3 and not any("." in k for k in keys)
    for bad in ("a b", "a<b", "a?b", "a#b", "a%b", ".hidden", ""):
        with pytest.raises(ValueError, match="letters, digits"):
            safe_name("clip id", bad)
    assert safe_name("clip id", "egodex-add_remove_lid-0.v2") == "egodex-add_remove_lid-0.v2"


def test_a_shard_not_verified_when_written_is_never_reused(released):
    """A parent's shard whose bytes were not checked against the store when it was written
    (a release made before the check) is written again, verified, not reused."""
    import json as js
    import shutil as sh

    rel = released["tmp"] / "unverified"
    sh.copytree(released["rel"], rel)
    for sidecar in (rel / "shards").glob("*.json"):
        info = js.loads(sidecar.read_text())
        info.pop("verified", None)
        sidecar.write_text(js.dumps(info))
    latest = versions(Location(rel))[-1]
    path = rel / latest / "manifest.json"
    m = js.loads(path.read_text())
    for s in m["shards"]:
        s.pop("verified", None)
    path.write_text(js.dumps(m))
    argv = ["release", "--from", str(released["run"]), "--out", str(rel), "--shard-mb", SHARD_MB,
            "--address", released["cluster"].scheduler_address]
    assert main(argv) == 0
    new = read_release(Location(rel), versions(Location(rel))[-1])
    assert new["version"] != latest and new["counts"]["shards_reused"] == 0
    assert all(s["verified"] for s in new["shards"])
