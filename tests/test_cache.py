"""Checkpoint integrity, the cache location and the cache command."""

import pytest
import torch

from kkl_bench.cli import main
from kkl_bench.kkl.cache import CheckpointCache
from kkl_bench.support import cache
from kkl_bench.support.cache import cache_info, default_cache_dir

DESCRIPTION = {"kind": "test", "value": 1}


def stored(tmp_path):
    cache = CheckpointCache(tmp_path)
    path = cache.save("test-kind", DESCRIPTION, {"weights": torch.arange(1000.0)})
    return cache, path


def test_a_checkpoint_round_trips(tmp_path):
    cache, _ = stored(tmp_path)
    torch.testing.assert_close(
        cache.load("test-kind", DESCRIPTION)["weights"], torch.arange(1000.0)
    )
    assert cache.load("test-kind", {**DESCRIPTION, "value": 2}) is None  # another key


@pytest.mark.parametrize("damage", ["truncate", "flip", "no checksum"])
def test_a_damaged_checkpoint_is_discarded_not_loaded(tmp_path, damage):
    cache, path = stored(tmp_path)
    data = bytearray(path.read_bytes())
    if damage == "truncate":
        path.write_bytes(data[: len(data) // 2])
    elif damage == "flip":
        data[len(data) // 2] ^= 0xFF
        path.write_bytes(bytes(data))
    else:
        path.with_name(path.name + ".sha256").unlink()
    assert cache_info(tmp_path)[0].damaged == 1
    with pytest.warns(UserWarning, match="discarding damaged checkpoint"):
        assert cache.load("test-kind", DESCRIPTION) is None
    assert not path.exists()  # removed, so the next fit rebuilds it


def test_cache_location_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("KKL_BENCH_CACHE", str(tmp_path / "elsewhere"))
    assert default_cache_dir() == tmp_path / "elsewhere"
    monkeypatch.delenv("KKL_BENCH_CACHE")
    assert str(default_cache_dir()) == ".kkl_bench_cache"


def test_cache_command_reports_and_clears(tmp_path, capsys):
    checkpoints, _ = stored(tmp_path)
    with checkpoints.claim("test-kind", DESCRIPTION):  # leaves its lock file, empty
        pass
    assert cache_info(tmp_path)[0].entries == 1 and cache_info(tmp_path)[0].damaged == 0
    assert main(["cache", "info", "--cache", str(tmp_path)]) == 0
    assert "test-kind: 1 entries" in capsys.readouterr().out
    assert main(["cache", "clear", "--cache", str(tmp_path)]) == 0
    assert not tmp_path.exists()
    assert main(["cache", "info", "--cache", str(tmp_path)]) == 0
    assert "(empty)" in capsys.readouterr().out


def test_an_unwritable_results_directory_fails_before_any_work(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    assert main(["run", "--estimator", "ekf", "--results", str(blocker / "results")]) == 2
    error = capsys.readouterr().err
    assert f"results directory {blocker / 'results'} is not writable" in error


@pytest.mark.parametrize("jobs", ["0", "-1", "two"])
def test_invalid_jobs_exit_with_usage(jobs, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["run", "--estimator", "ekf", "--jobs", jobs])
    assert exit_info.value.code == 2
    assert f"jobs must be a positive integer, got '{jobs}'" in capsys.readouterr().err


def test_a_change_to_any_source_file_changes_the_code_digest(tmp_path, monkeypatch):
    (tmp_path / "sub").mkdir()
    (tmp_path / "kernels.py").write_text("x = 1\n")
    (tmp_path / "sub" / "model.py").write_text("y = 2\n")
    monkeypatch.setattr(cache, "_paths", lambda subpackage: [str(tmp_path)])
    digests = [cache.code_digest.__wrapped__()]
    (tmp_path / "sub" / "model.py").write_text("y = 3\n")  # any file of the package
    digests.append(cache.code_digest.__wrapped__())
    (tmp_path / "sub" / "model.py").write_text("y = 3\n")
    digests.append(cache.code_digest.__wrapped__())
    assert digests[0] != digests[1] == digests[2]


def test_the_imported_code_digest_follows_imports_through_modules_and_functions(
    tmp_path, monkeypatch
):
    """``drawing`` imports ``style`` at its top, ``labels`` inside a function, which
    imports ``titles``, and tries ``optional``, which is not there; ``unused`` is imported
    by none of them."""
    package = tmp_path / "digestpkg"
    package.mkdir()
    sources = {
        "__init__.py": "",
        "drawing.py": "import numpy\nfrom digestpkg import style\n\n\ndef draw():\n"
        "    from digestpkg.labels import LABEL\n    return LABEL\n\n\n"
        "try:\n    import digestpkg.optional\nexcept ImportError:\n    pass\n",
        "style.py": "COLOUR = 'k'\n",
        "labels.py": "from digestpkg.titles import TITLE as LABEL\n",
        "titles.py": "TITLE = 't'\n",
        "unused.py": "x = 1\n",
    }
    for name, source in sources.items():
        (package / name).write_text(source)
    monkeypatch.syspath_prepend(str(tmp_path))
    assert cache.imported_modules("digestpkg.drawing") == [
        f"digestpkg.{name}" for name in ("drawing", "labels", "optional", "style", "titles")
    ]
    digests = [cache.imported_code_digest.__wrapped__("digestpkg.drawing")]
    (package / "unused.py").write_text("x = 2\n")
    digests.append(cache.imported_code_digest.__wrapped__("digestpkg.drawing"))
    (package / "titles.py").write_text("TITLE = 'T'\n")  # two imports away, in a function
    digests.append(cache.imported_code_digest.__wrapped__("digestpkg.drawing"))
    assert digests[0] == digests[1] != digests[2]


def test_the_figures_draw_on_none_of_the_estimators_or_systems_code():
    """What keeps a board's figures through a change to an estimator: that change reaches
    a figure only through the results it draws."""
    drawing = cache.imported_modules("kkl_bench.analysis.figures")
    assert {
        "kkl_bench.analysis.figures",
        "kkl_bench.families",
        "kkl_bench.analysis.summary",
    } <= set(drawing)
    assert not [
        name for name in drawing if name.startswith(("kkl_bench.estimators", "kkl_bench.systems"))
    ]


def test_trained_models_travel_by_export_and_import_and_nothing_else_does(tmp_path, capsys):
    """The models of one cache reach another machine's through a folder: only whole,
    checksummed models (the checkpoints of trainings under way when asked), never over an
    intact model already there, over a half-copied one."""
    here, travelling, there = tmp_path / "here", tmp_path / "travelling", tmp_path / "there"
    _, model = stored(here)
    damaged = CheckpointCache(here).save("test-kind", {**DESCRIPTION, "value": 2}, {"w": 1})
    damaged.with_name(damaged.name + ".sha256").write_text("0" * 64)
    CheckpointCache(here).save("kkl-resume", DESCRIPTION, {"step": 7})
    (here / "test-kind" / f"{model.name}.lock").write_text("")
    (here / "bound_kernels").mkdir()
    (here / "bound_kernels" / "kernel.py").write_text("")

    assert main(["cache", "export", str(travelling), "--cache", str(here)]) == 0
    assert "exported 1 model (" in capsys.readouterr().out
    assert sorted(p.relative_to(travelling).as_posix() for p in travelling.rglob("*")) == [
        "test-kind",
        f"test-kind/{model.name}",
        f"test-kind/{model.name}.sha256",
    ]
    interrupted = there / "test-kind" / model.name  # an earlier import cut before the sidecar
    interrupted.parent.mkdir(parents=True)
    interrupted.write_bytes(model.read_bytes()[:100])
    assert main(["cache", "import", str(travelling), "--cache", str(there)]) == 0
    assert "imported 1 model (" in capsys.readouterr().out
    torch.testing.assert_close(
        CheckpointCache(there).load("test-kind", DESCRIPTION)["weights"], torch.arange(1000.0)
    )
    assert main(["cache", "export", str(travelling), "--cache", str(here)]) == 0
    out = capsys.readouterr().out
    assert "exported 0 models" in out and "1 already there; 1 left (damaged" in out

    assert (
        main(["cache", "export", str(travelling), "--with-checkpoints", "--cache", str(here)]) == 0
    )
    assert CheckpointCache(travelling).load("kkl-resume", DESCRIPTION) == {
        "step": 7,
        "description": '{"kind": "test", "value": 1}',
    }


def test_an_export_with_checkpoints_is_a_snapshot_and_an_import_keeps_those_already_there(
    tmp_path, capsys
):
    """A checkpoint's key names a training whose state moves on: an export replaces the
    folder's older checkpoint and drops those of trainings that finished; an import never
    replaces one the cache holds (a training there may be resuming from it)."""
    here, travelling, there = tmp_path / "here", tmp_path / "travelling", tmp_path / "there"
    under_way = {**DESCRIPTION, "slot": 0}
    finished = {**DESCRIPTION, "slot": 1}
    CheckpointCache(here).save("kkl-resume", under_way, {"step": 200})
    CheckpointCache(here).save("kkl-resume", finished, {"step": 400})

    def export() -> str:
        command = ["cache", "export", str(travelling), "--with-checkpoints", "--cache", str(here)]
        assert main(command) == 0
        return capsys.readouterr().out

    assert "exported 2 models" in export()
    CheckpointCache(here).save("kkl-resume", under_way, {"step": 600})
    CheckpointCache(here).remove("kkl-resume", finished)
    out = export()
    assert "exported 1 model (" in out and "dropped 1 checkpoint of finished trainings" in out
    assert CheckpointCache(travelling).load("kkl-resume", under_way)["step"] == 600
    assert CheckpointCache(travelling).load("kkl-resume", finished) is None
    assert sorted(p.name for p in (travelling / "kkl-resume").iterdir()) == sorted(
        p.name for p in (here / "kkl-resume").iterdir()
    )

    CheckpointCache(there).save("kkl-resume", under_way, {"step": 800})
    command = ["cache", "import", str(travelling), "--with-checkpoints", "--cache", str(there)]
    assert main(command) == 0
    assert "imported 0 models" in capsys.readouterr().out
    assert CheckpointCache(there).load("kkl-resume", under_way)["step"] == 800


def test_export_and_import_need_a_folder_and_the_others_take_none(tmp_path, capsys):
    assert main(["cache", "export", "--cache", str(tmp_path)]) == 2
    assert "kkl-bench cache export needs a FOLDER" in capsys.readouterr().err
    assert main(["cache", "info", str(tmp_path), "--cache", str(tmp_path)]) == 2
    assert main(["cache", "import", str(tmp_path / "absent"), "--cache", str(tmp_path)]) == 2
    assert "nothing to import" in capsys.readouterr().err
