"""usdml's layers point one way (docs/architecture.md, "Layers"): every import of every module of the
package, at module level or inside a function, read from the source with ``ast``.

    commands ──► render ──► lighting ──► visibility ──► scene
                   │  └──────────────────────────────►  ▲
                   ├──► stage ───────────────────────────┘
                   └──► aov

A layer may import its own modules, the layers :data:`MAY_IMPORT` names, the leaves and the package
itself; nothing climbs back. Leaves (errors, parameters and settings, the cache, the thread pool, the
native loader, the backends' name registry, the methods' parameter rows, ...) hold no rendering and import only leaves, so any layer
may use them. ``kernels/`` (installed as ``usdml.kernels``) imports only itself. No module imports a
private name (``_x``) of another usdml module (issue 20).
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: where the package's modules are on disk (pyproject.toml's package-dir)
PACKAGE_DIRS = {"usdml": ROOT / "usdml", "usdml.kernels": ROOT / "kernels", "usdml.schemas": ROOT / "schemas"}

#: the layer of each module, by the longest matching name; every module of the package must have one
LAYER_OF = {
    "usdml.cli": "commands", "usdml.recorder": "commands", "usdml.compare": "commands", "usdml.bench": "commands",
    "usdml.info": "commands", "usdml.view": "commands", "usdml.plots": "commands", "usdml.reference": "commands",
    "usdml.render": "render",
    "usdml.lighting": "lighting",
    "usdml.visibility": "visibility",
    "usdml.stage": "stage",
    "usdml.scene": "scene",
    "usdml.aov": "aov",
    "usdml.kernels": "kernels",
    # leaves: no rendering, only other leaves imported
    "usdml.errors": "leaf", "usdml.params": "leaf", "usdml.settings": "leaf", "usdml.outputs": "leaf",
    "usdml.zorder": "leaf", "usdml.cache": "leaf", "usdml.parallel": "leaf", "usdml.native": "leaf",
    "usdml.schemas": "leaf", "usdml.visibility.registry": "leaf", "usdml.param": "leaf",
    # a method's rows of the parameter table, in its folder: they import only usdml.param
    "usdml.visibility.voxel.params": "leaf", "usdml.visibility.svo.params": "leaf",
    "usdml.visibility.insm.params": "leaf", "usdml.lighting.lgh.params": "leaf", "usdml.lighting.area.params": "leaf",
    "usdml.render.denoise.params": "leaf",
    # the preview surface's material rows and their NumPy reference (NumPy only): the scene writes rows, lighting
    # and the kernels read them
    "usdml.kernels.brdf": "leaf",
}

#: the layers each layer may import besides its own, the leaves and the package (``usdml``: the version, and
#: the pipeline API it hands out on first use)
MAY_IMPORT = {
    "commands": {"render", "lighting", "visibility", "stage", "scene", "aov", "kernels"},
    "render": {"lighting", "visibility", "stage", "scene", "aov", "kernels"},
    "lighting": {"visibility", "scene", "kernels"},
    "visibility": {"scene", "kernels"},
    "stage": {"scene"},
    "scene": set(),
    "aov": set(),
    "leaf": set(),
    "kernels": set(),
}

#: the layers that read USD (``pxr``): the scene delegate, frame naming's FrameSpec, the commands
PXR = {"stage", "aov", "commands"}


def modules() -> dict[str, Path]:
    """Every module of the package by its import name."""
    found = {}
    for package, folder in PACKAGE_DIRS.items():
        for path in folder.rglob("*.py"):
            parts = list(path.relative_to(folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            found[".".join([package, *parts])] = path
    return found


MODULES = modules()


def layer_of(module: str) -> str | None:
    if module == "usdml":
        return "package"
    match = max((name for name in LAYER_OF if module == name or module.startswith(name + ".")), key=len, default=None)
    return LAYER_OF.get(match) if match else None


def imports(path: Path, module: str):
    """``(line, imported module, name or None)`` of every import of ``path``; ``from a import b`` names
    module ``a.b`` where that is a module, else ``a`` and the name ``b``."""
    tree = ast.parse(path.read_text(), str(path))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name, None
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([base] if base else []))
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                yield (node.lineno, sub, None) if sub in MODULES else (node.lineno, base, alias.name)


def violations() -> list[str]:
    bad = []
    for module, path in sorted(MODULES.items()):
        layer = layer_of(module)
        if layer is None:
            bad.append(f"{module}: in no layer (add it to LAYER_OF)")
            continue
        for line, target, name in imports(path, module):
            where = f"{path.relative_to(ROOT)}:{line}"
            if target == "pxr" or target.startswith("pxr."):
                if layer not in PXR and module != "usdml.schemas":
                    bad.append(f"{where}: {layer} module {module} imports pxr")
                continue
            if target != "usdml" and not target.startswith("usdml."):
                continue
            if name is not None and name.startswith("_") and not name.startswith("__") and target != module:
                bad.append(f"{where}: {module} imports the private name {name} of {target}")
            other = layer_of(target)
            if layer == "package" or other in (layer, "package"):
                continue
            if layer == "kernels" or (other != "leaf" and other not in MAY_IMPORT[layer]):
                bad.append(f"{where}: {layer} module {module} imports {target} ({other})")
    return bad


def test_every_module_has_a_layer():
    assert "usdml.visibility.base" in MODULES and "usdml.kernels.voxel.query" in MODULES
    assert [m for m in MODULES if layer_of(m) is None] == []


def test_imports_point_down_the_layers():
    assert violations() == []


def test_the_check_sees_imports_inside_functions(tmp_path):
    """An import in a function body counts as one at the top."""
    source = tmp_path / "m.py"
    source.write_text("def f():\n    from usdml.lighting.direct import shade_direct\n    from usdml.parallel import _x\n")
    found = list(imports(source, "usdml.visibility.m"))
    assert (2, "usdml.lighting.direct", "shade_direct") in found and (3, "usdml.parallel", "_x") in found


#: the methods (a paper each) that own a folder: the visibility backends but the reference, and the LGH
METHOD_FOLDERS = {"usdml.visibility": ("voxel", "svo", "insm"), "usdml.lighting": ("lgh",),
                  "usdml.kernels": ("voxel", "svo", "insm", "lgh")}


def test_each_method_lives_in_its_folder():
    """A method's modules, Python or C, are in its folder (``usdml/visibility/voxel/``, ``kernels/voxel/``), not
    beside the folder with the method's name in front (``voxel_array.py``); every registered backend but the
    reference has its folder."""
    from usdml.visibility.registry import backend_names

    assert set(backend_names()) - {"exact"} <= set(METHOD_FOLDERS["usdml.visibility"])
    flat = []
    for package, methods in METHOD_FOLDERS.items():
        folder = MODULES[package].parent
        for method in methods:
            assert (folder / method / "__init__.py").is_file(), f"{package}.{method} is not a folder"
            flat += [p.name for p in folder.iterdir() if p.is_file() and p.name.startswith(method)]
    c_files = {p.name for p in PACKAGE_DIRS["usdml.kernels"].iterdir() if p.suffix in (".c", ".h")}
    assert flat == [] and c_files == set()


def test_pyproject_installs_every_package():
    """A plain ``pip install .`` (not editable) installs only the packages pyproject.toml lists: every folder of
    the package with an ``__init__.py`` must be there (usdml.lighting.area was missing, unseen by editable
    installs)."""
    import tomllib

    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    on_disk = {".".join((name, *init.parent.relative_to(folder).parts)) for name, folder in PACKAGE_DIRS.items()
               for init in folder.rglob("__init__.py") if "__pycache__" not in init.parts}
    assert on_disk - listed == set()
