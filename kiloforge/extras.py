"""Which extra of ``pyproject.toml`` installs each optional dependency, and the one line for a missing one."""
from __future__ import annotations

#: top-level module of an optional dependency -> the extra that installs it (pyproject.toml)
EXTRAS = {"torch": "learn", "tyro": "learn", "tensorboard": "learn", "onnx": "onnx", "onnxruntime": "onnx",
          "ray": "sweep", "pettingzoo": "pettingzoo", "gymnasium": "pettingzoo"}
#: top-level module of a core dependency -> its distribution (a broken install: it is installed with kiloforge)
CORE = {"numpy": "numpy", "jinja2": "jinja2", "matplotlib": "matplotlib", "PIL": "pillow", "tqdm": "tqdm"}


def missing_extra(err: ModuleNotFoundError) -> tuple[str, str] | None:
    """(module, extra) when ``err`` is a missing optional dependency, else None."""
    top = (err.name or "").partition(".")[0]
    return (top, EXTRAS[top]) if top in EXTRAS else None


def missing_dependency(prog: str, err: ModuleNotFoundError) -> str | None:
    """The one line for a missing dependency of kiloforge (``<prog> needs <module>: pip install ...``),
    None when ``err`` names a module kiloforge does not depend on."""
    missing = missing_extra(err)
    if missing is not None:
        return f"{prog} needs {missing[0]}: pip install 'kiloforge[{missing[1]}]'"
    top = (err.name or "").partition(".")[0]
    return f"{prog} needs {top} (a dependency of kiloforge): pip install {CORE[top]}" if top in CORE else None
