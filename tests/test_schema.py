"""usdml's codeless UsdmlRenderSettingsAPI schema (schemas/, tools/gen_schema.py).

USD builds ``Usd.SchemaRegistry`` once per process and ignores plugins registered afterwards, so
whatever touches the registry runs in a fresh subprocess: the result cannot depend on which test
file pytest imported first.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import usdml.schemas as schemas

REPO = Path(__file__).resolve().parent.parent
GEN_SCHEMA = REPO / "tools" / "gen_schema.py"

# Runs in a fresh interpreter; prints one JSON object describing what USD sees.
PROBE = textwrap.dedent(
    """
    import json, sys
    {setup}
    from pxr import Sdf, Usd, UsdGeom, UsdRender

    name = "UsdmlRenderSettingsAPI"
    out = {{"registered": registered}}
    defn = Usd.SchemaRegistry().FindAppliedAPIPrimDefinition(name)
    out["found"] = defn is not None
    if defn is not None:
        out["attrs"] = {{}}
        for prop in defn.GetPropertyNames():
            a = defn.GetAttributeDefinition(prop)
            tokens = a.GetMetadata("allowedTokens")
            out["attrs"][prop] = {{
                "fallback": a.GetFallbackValue(),
                "pytype": type(a.GetFallbackValue()).__name__,
                "typeName": str(a.GetTypeName()),
                "uniform": a.GetVariability() == Sdf.VariabilityUniform,
                "allowedTokens": list(tokens) if tokens else None,
                "doc": a.GetDocumentation(),
            }}
        out["doc"] = defn.GetDocumentation()
        out["singleApply"] = (Usd.SchemaRegistry.IsAppliedAPISchema(name)
                              and not Usd.SchemaRegistry.IsMultipleApplyAPISchema(name))

        stage = Usd.Stage.CreateInMemory()
        settings = UsdRender.Settings.Define(stage, "/Render/Settings").GetPrim()
        can = settings.CanApplyAPI(name)
        out["canApplySettings"] = bool(can)
        out["applied"] = bool(settings.ApplyAPI(name))
        out["hasAPI"] = settings.HasAPI(name)
        out["appliedSchemas"] = list(settings.GetAppliedSchemas())
        res = settings.GetAttribute("usdml:voxel:resolution")
        out["resolution"] = res.Get()
        out["resolutionAuthored"] = res.IsAuthored()
        out["visibility"] = settings.GetAttribute("usdml:visibility").Get()
        settings.GetAttribute("usdml:vpl:count").Set(5000)
        out["vplAuthored"] = settings.GetAttribute("usdml:vpl:count").Get()

        mesh = UsdGeom.Mesh.Define(stage, "/Mesh").GetPrim()
        can = mesh.CanApplyAPI(name)
        out["canApplyMesh"] = bool(can)
        out["whyNotMesh"] = can.whyNot
    print(json.dumps(out))
    """
)

REGISTER = "import usdml.schemas as s\nregistered = s.register()\nregistered_again = s.register()\nassert registered == registered_again"
NO_REGISTER = "registered = None"


def _probe(setup: str, env: dict[str, str]) -> dict:
    proc = subprocess.run([sys.executable, "-c", PROBE.format(setup=setup)], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "rror" not in proc.stderr and "arning" not in proc.stderr, proc.stderr  # Tf diagnostics
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _clean_env() -> dict[str, str]:
    env = dict(os.environ)
    env.pop("PXR_PLUGINPATH_NAME", None)
    return env


@pytest.fixture(scope="module")
def registered() -> dict:
    """What USD sees in a fresh process after ``usdml.schemas.register()``."""
    return _probe(REGISTER, _clean_env())


def test_register_finds_schema(registered):
    assert registered["registered"] is True
    assert registered["found"]
    assert registered["singleApply"]
    assert registered["doc"].startswith("usdml's render settings")


@pytest.mark.parametrize("attr", schemas.ATTRIBUTES, ids=lambda a: a.name)
def test_prim_definition_fallbacks(registered, attr):
    got = registered["attrs"][attr.name]
    assert got["uniform"]
    assert got["pytype"] == attr.type.__name__
    if attr.type is float:
        assert math.isclose(got["fallback"], attr.default)
    else:
        assert got["fallback"] == attr.default
    assert got["doc"], f"{attr.name} has no documentation in generatedSchema.usda"


def test_attributes_match_prim_definition(registered):
    assert [a.name for a in schemas.ATTRIBUTES] and \
        set(registered["attrs"]) == {a.name for a in schemas.ATTRIBUTES}
    for name, tokens in schemas.ALLOWED_TOKENS.items():
        assert registered["attrs"][name]["allowedTokens"] == list(tokens)
    untokened = {n for n, a in registered["attrs"].items() if a["allowedTokens"]} - set(schemas.ALLOWED_TOKENS)
    assert not untokened
    expected_types = {str: "token", int: "int", float: "float", bool: "bool"}
    for a in schemas.ATTRIBUTES:
        assert registered["attrs"][a.name]["typeName"] == expected_types[a.type]
    assert schemas.ATTRIBUTES[0].default in schemas.ALLOWED_TOKENS["usdml:visibility"]


def test_apply_to_render_settings(registered):
    assert registered["canApplySettings"]
    assert registered["applied"] and registered["hasAPI"]
    assert registered["appliedSchemas"] == [schemas.SCHEMA_NAME]
    # fallbacks come from the schema, nothing authored
    assert registered["resolution"] == 128 and not registered["resolutionAuthored"]
    assert registered["visibility"] == "exact"
    assert registered["vplAuthored"] == 5000


def test_cannot_apply_to_mesh(registered):
    assert not registered["canApplyMesh"]
    assert "RenderSettings" in registered["whyNotMesh"]
    # (Usd.Prim.ApplyAPI itself does not check CanApplyAPI; callers that author must.)


def test_plugin_path_env_without_register():
    """Any USD tool finds the schema through PXR_PLUGINPATH_NAME=PLUGIN_DIR, without usdml."""
    env = _clean_env()
    env["PXR_PLUGINPATH_NAME"] = str(schemas.PLUGIN_DIR)
    seen = _probe(NO_REGISTER + "\nassert 'usdml' not in sys.modules", env)
    assert seen["found"]
    assert seen["resolution"] == 128
    assert not seen["canApplyMesh"]


def test_without_plugin_schema_is_unknown():
    """Control for the test above: a plain process does not know the schema."""
    seen = _probe(NO_REGISTER, _clean_env())
    assert not seen["found"]


def test_import_does_not_load_pxr():
    code = ("import importlib.util, sys\n"
            f"spec = importlib.util.spec_from_file_location('s', {str(REPO / 'schemas' / '__init__.py')!r})\n"
            "m = importlib.util.module_from_spec(spec); spec.loader.exec_module(m)\n"
            "assert 'pxr' not in sys.modules, 'pxr imported'\n"
            "print(m.PLUGIN_DIR)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert Path(proc.stdout.strip()) == schemas.PLUGIN_DIR


def test_plugin_dir_contents():
    assert isinstance(schemas.PLUGIN_DIR, Path)
    for name in ("schema.usda", "generatedSchema.usda", "plugInfo.json"):
        assert (schemas.PLUGIN_DIR / name).is_file()
    info = json.loads("".join(l for l in (schemas.PLUGIN_DIR / "plugInfo.json").read_text().splitlines(True)
                              if not l.lstrip().startswith("#")))
    (plugin,) = info["Plugins"]
    assert plugin["Type"] == "resource" and plugin["Name"] == "usdml" and plugin["LibraryPath"] == ""
    types = plugin["Info"]["Types"]
    assert set(types) == {"Usdml" + schemas.SCHEMA_NAME, "UsdmlUsdmlLightGroupAPI"}
    entry = types["Usdml" + schemas.SCHEMA_NAME]
    assert entry["alias"] == {"UsdSchemaBase": schemas.SCHEMA_NAME}
    assert entry["apiSchemaCanOnlyApplyTo"] == list(schemas.APPLIES_TO)
    assert entry["schemaKind"] == "singleApplyAPI" and entry["bases"] == ["UsdAPISchemaBase"]
    group = types["UsdmlUsdmlLightGroupAPI"]
    assert group["alias"] == {"UsdSchemaBase": "UsdmlLightGroupAPI"} and group["schemaKind"] == "singleApplyAPI"


def test_light_group_api_declares_the_attribute_usdml_reads():
    """Applying UsdmlLightGroupAPI gives a light the ``usdml:lightGroup`` string the renderer reads."""
    from pxr import Usd, UsdLux

    from usdml.stage.linking import GROUP_ATTRIBUTE

    stage = Usd.Stage.CreateInMemory()
    light = UsdLux.SphereLight.Define(stage, "/L").GetPrim()
    assert light.ApplyAPI("UsdmlLightGroupAPI")
    attr = light.GetAttribute(GROUP_ATTRIBUTE)
    assert attr and attr.GetTypeName() == "string" and attr.Get() == ""


def test_generated_files_up_to_date():
    proc = subprocess.run([sys.executable, str(GEN_SCHEMA), "--check"], cwd=REPO,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_check_detects_stale_files(tmp_path):
    """--check fails when schema.usda's attributes are not the parameter table's, or when the generated
    files are not schema.usda's; regenerating fixes both."""
    for name in ("schema.usda", "generatedSchema.usda", "plugInfo.json"):
        shutil.copy(schemas.PLUGIN_DIR / name, tmp_path / name)
    schema, generated = tmp_path / "schema.usda", tmp_path / "generatedSchema.usda"

    def run(*args):
        return subprocess.run([sys.executable, str(GEN_SCHEMA), str(schema), *args],
                              capture_output=True, text=True, timeout=120)

    assert run("--check").returncode == 0
    # a hand edit of a table attribute in schema.usda: stale against usdml/params.py, and undone
    schema.write_text(schema.read_text().replace("uniform int usdml:seed = 0", "uniform int usdml:seed = 7"))
    stale = run("--check")
    assert stale.returncode == 1 and "-    uniform int usdml:seed = 7" in stale.stdout
    assert "schema.usda" in stale.stderr and "generatedSchema.usda" not in stale.stderr
    assert run().returncode == 0 and run("--check").returncode == 0
    assert schema.read_text() == (schemas.PLUGIN_DIR / "schema.usda").read_text()
    # a stale generated file
    generated.write_text(generated.read_text().replace("uniform int usdml:seed = 0", "uniform int usdml:seed = 7"))
    stale = run("--check")
    assert stale.returncode == 1 and "generatedSchema.usda" in stale.stderr and "usdml:seed = 7" in stale.stdout
    assert run().returncode == 0 and run("--check").returncode == 0
    # regeneration is deterministic and keeps the files as they were
    for name in ("schema.usda", "generatedSchema.usda", "plugInfo.json"):
        assert (tmp_path / name).read_text() == (schemas.PLUGIN_DIR / name).read_text(), name


def test_schema_outside_the_table_is_kept(tmp_path):
    """Only UsdmlRenderSettingsAPI's body is the table's: the layer's doc and class metadata stay as written."""
    for name in ("schema.usda", "generatedSchema.usda", "plugInfo.json"):
        shutil.copy(schemas.PLUGIN_DIR / name, tmp_path / name)
    schema = tmp_path / "schema.usda"
    schema.write_text(schema.read_text().replace("usdml's render settings, applied", "usdml's settings, applied"))
    assert subprocess.run([sys.executable, str(GEN_SCHEMA), str(schema)], capture_output=True, timeout=120).returncode == 0
    assert 'doc = """usdml\'s settings, applied' in schema.read_text()
    assert "usdml's settings, applied" in (tmp_path / "generatedSchema.usda").read_text()


def test_settings_defaults_agree():
    """usdml.settings maps the schema attributes onto its dataclass; the defaults must agree."""
    settings = pytest.importorskip("usdml.settings")
    mapping = getattr(settings, "SCHEMA_ATTRIBUTES", None)
    if mapping is None:
        pytest.skip("usdml.settings has no SCHEMA_ATTRIBUTES")
    assert set(mapping) == {a.name for a in schemas.ATTRIBUTES}
    defaults = settings.UsdmlSettings().as_dict()
    for a in schemas.ATTRIBUTES:
        assert defaults[mapping[a.name]] == a.default, a.name

