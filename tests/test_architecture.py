"""The package's layers (docs/architecture.md): imports only go down, and no script imports another script; the
product (``nrc/``) and the lab (``scripts/``, its shared code in ``scripts/lab/``) stay apart: the product never imports
the lab nor locates the checkout, and the lab uses only the product's public names."""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

from conftest import REPO

# lower number = lower layer; a module may import its own layer and the ones below
LAYERS = {
    "nrc.errors": 0, "nrc.config": 0,
    "nrc.io": 1, "nrc.volume": 1, "nrc.camera": 1, "nrc.denoise": 1, "nrc.metrics": 1,
    "nrc.transport": 2, "nrc.scene": 2,
    "nrc.cache": 3,
    "nrc.render": 4,
    "nrc.evaluation": 5,
    "nrc.app": 6, "nrc.api": 6, "nrc.reference_app": 6, "nrc.__main__": 6, "nrc": 6,  # the package root re-exports
}


def layer_of(module: str) -> int | None:
    best = None
    for prefix, layer in LAYERS.items():
        if module == prefix or (prefix != "nrc" and module.startswith(prefix + ".")):
            if best is None or len(prefix) > len(best[0]):
                best = (prefix, layer)
    return None if best is None else best[1]


def imports(path: Path) -> list[str]:
    tree = ast.parse(path.read_text())
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.append(node.module)
    return out


def test_imports_only_go_down():
    bad = []
    for path in sorted((REPO / "nrc").rglob("*.py")):
        module = ".".join(path.relative_to(REPO).with_suffix("").parts).removesuffix(".__init__")
        own = layer_of(module)
        assert own is not None, f"{module} has no layer in docs/architecture.md"
        for target in imports(path):
            if target.startswith("nrc"):
                layer = layer_of(target)
                if layer is not None and layer > own:
                    bad.append(f"{module} (layer {own}) imports {target} (layer {layer})")
    assert not bad, "\n".join(bad)


def test_no_script_imports_another_script():
    scripts = {p.stem for p in (REPO / "scripts").glob("*.py")}
    bad = [f"{p.name} imports {t}" for p in (REPO / "scripts").rglob("*.py") for t in imports(p)
           if t.split(".")[0] in scripts]
    assert not bad, bad


def test_no_script_edits_sys_path():
    """Scripts import the installed package (``pip install -e .``), never the checkout through ``sys.path``."""
    bad = []
    for p in sorted((REPO / "scripts").rglob("*.py")):
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.Attribute) and node.attr == "path" and isinstance(node.value, ast.Name) \
                    and node.value.id == "sys":
                bad.append(f"{p.name}:{node.lineno}")
    assert not bad, bad


def test_renderer_components_take_their_settings_whole():
    """Settings travel whole (one new setting must not touch a chain of signatures): the NRC renderer's tracer and
    the path tracer take the scene, the estimator and their settings dataclass, not one argument per key."""
    import inspect

    from nrc.render.radiance_caching.paths import NRCPathTracer
    from nrc.render.radiance_caching.renderer import NRCRenderer
    from nrc.render.pt import PathTracer

    for cls in (NRCPathTracer, NRCRenderer, PathTracer):
        params = [p for p in inspect.signature(cls.__init__).parameters if p != "self"]
        assert len(params) <= 6, f"{cls.__name__}.__init__ takes {len(params)} parameters: {params}"


def test_renderers_take_settings_not_the_raw_config():
    """Renderers take their typed settings (read and resolved once: nrc.render.registry), never the raw config: no
    renderer's ``__init__`` takes a ``DictConfig`` or a ``cfg``, and their modules do not import OmegaConf's."""
    import inspect

    from nrc.render.preview import PreviewRenderer
    from nrc.render.pt import PathTracer
    from nrc.render.radiance_caching.renderer import NRCRenderer

    for cls in (NRCRenderer, PathTracer, PreviewRenderer):
        params = inspect.signature(cls.__init__).parameters
        assert "cfg" not in params and "settings" in params, (cls.__name__, list(params))
        assert not any("DictConfig" in str(p.annotation) for p in params.values()), cls.__name__
        source = inspect.getsource(inspect.getmodule(cls))
        assert "DictConfig" not in source, inspect.getmodule(cls).__name__


def _is_settings(arg: ast.arg) -> bool:
    """A settings object: a parameter named ``settings`` or annotated with a ``...Settings`` / ``...Options`` type."""
    note = ast.unparse(arg.annotation) if arg.annotation is not None else ""
    return arg.arg == "settings" or note.endswith(("Settings", "Options"))


def test_no_init_takes_more_than_six_parameters():
    """Settings travel whole: no ``__init__`` in ``nrc/`` takes more than 6 parameters besides settings objects."""
    bad = []
    for path in sorted((REPO / "nrc").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef) and node.name == "__init__":
                a = node.args
                params = [p for p in (*a.posonlyargs, *a.args, *a.kwonlyargs)[1:] if not _is_settings(p)]
                if len(params) > 6:
                    bad.append(f"{path.relative_to(REPO)}:{node.lineno} takes {len(params)}")
    assert not bad, bad


# renderer features the integrator-agnostic core must not know (their renderers' vertex programs do)
CORE_FEATURES = re.compile(r"debias|reuse|cache_target", re.I)
CORE = REPO / "nrc" / "render" / "wavefront"


def code_lines(path: Path) -> dict[int, str]:
    """The lines of ``path`` that hold code (docstrings and comments left out), as their tokens joined."""
    src = path.read_text()
    docs: set[int] = set()
    for node in ast.walk(ast.parse(src)):
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
            docs |= set(range(node.lineno, node.end_lineno + 1))
    lines: dict[int, list[str]] = {}
    skip = (tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT, tokenize.ENDMARKER)
    for tok in tokenize.generate_tokens(io.StringIO(src).readline):
        if tok.type not in skip and tok.start[0] not in docs:
            lines.setdefault(tok.start[0], []).append(tok.string)
    return {n: " ".join(t) for n, t in lines.items()}


def test_the_core_names_no_renderer_feature():
    """The wavefront core schedules; what a renderer does at a vertex (debias, reuse, the cache target) is its
    vertex program's (nrc.render.wavefront.program): the core's code names such a feature on at most 6 lines."""
    hits = [f"{p.name}:{n}: {line}" for p in sorted(CORE.glob("*.py")) for n, line in code_lines(p).items()
            if CORE_FEATURES.search(line)]
    assert len(hits) <= 6, "\n".join(hits)


def test_the_feature_scan_sees_code_but_not_docstrings(tmp_path):
    """The scan above counts a feature named in code, not in a docstring or a comment."""
    f = tmp_path / "m.py"
    f.write_text('"""debias here is prose."""\nx = 1  # reuse in a comment\ny = cache_target = 2\n')
    found = [n for n, line in code_lines(f).items() if CORE_FEATURES.search(line)]
    assert found == [3]


# files a reader can hold: derivations go to the docs, code is split along its concepts
MAX_LINES = 500
MAX_DOCSTRING_LINES = 40


def oversized(paths: list[Path]) -> list[str]:
    """The files of ``paths`` over :data:`MAX_LINES` lines or with a module docstring over
    :data:`MAX_DOCSTRING_LINES` lines, each as ``path: what``."""
    bad = []
    for path in paths:
        src = path.read_text()
        lines = len(src.splitlines())
        doc = ast.get_docstring(ast.parse(src)) or ""
        if lines > MAX_LINES:
            bad.append(f"{path}: {lines} lines (at most {MAX_LINES})")
        if len(doc.splitlines()) > MAX_DOCSTRING_LINES:
            bad.append(f"{path}: a module docstring of {len(doc.splitlines())} lines (at most {MAX_DOCSTRING_LINES})")
    return bad


def test_no_module_is_too_long_to_hold():
    """No file in ``nrc/`` is over 500 lines, and no module docstring over 40 (derivations belong in ``docs/``)."""
    bad = [b.replace(str(REPO) + "/", "") for b in oversized(sorted((REPO / "nrc").rglob("*.py")))]
    assert not bad, "\n".join(bad)


def test_the_size_check_can_fail(tmp_path):
    """The check above flags a long file and a long module docstring, and passes files at the limits."""
    fine, long_code, long_doc = tmp_path / "fine.py", tmp_path / "long_code.py", tmp_path / "long_doc.py"
    doc = '"""' + "\n".join(f"line {i}" for i in range(MAX_DOCSTRING_LINES)) + '"""\n'
    fine.write_text(doc + "x = 1\n" * (MAX_LINES - MAX_DOCSTRING_LINES))
    long_code.write_text("x = 1\n" * (MAX_LINES + 1))
    long_doc.write_text('"""' + "\n".join(f"line {i}" for i in range(MAX_DOCSTRING_LINES + 1)) + '"""\n')
    found = oversized([fine, long_code, long_doc])
    assert len(found) == 2, found
    assert "long_code.py: 501 lines" in found[0] and "long_doc.py: a module docstring of 41" in found[1]


# ---------------------------------------------------------------------------- the product and the lab apart
LAB = ("scripts", "lab")  # the lab's top-level names (scripts/ itself, its shared package)


def lab_imports(path: Path) -> list[str]:
    """The imports of ``path`` that reach the lab."""
    return [t for t in imports(path) if t.split(".")[0] in LAB]


def test_the_product_never_imports_the_lab():
    bad = [f"{p.relative_to(REPO)} imports {t}" for p in sorted((REPO / "nrc").rglob("*.py")) for t in lab_imports(p)]
    assert not bad, bad


def private_uses(path: Path) -> list[str]:
    """Underscore names of ``nrc`` a script uses: imported from an ``nrc`` module, or an attribute ``x._name`` read
    off anything (a script's own underscore names are plain names, never attributes of an object; dunders pass)."""
    def private(name: str) -> bool:
        return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))

    tree = ast.parse(path.read_text())
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "nrc":
            out += [f"{path.name}:{node.lineno}: from {node.module} import {a.name}" for a in node.names
                    if private(a.name) or any(private(part) for part in node.module.split("."))]
        elif isinstance(node, ast.Import):
            out += [f"{path.name}:{node.lineno}: import {a.name}" for a in node.names
                    if a.name.split(".")[0] == "nrc" and any(private(part) for part in a.name.split("."))]
        elif isinstance(node, ast.Attribute) and private(node.attr):
            out.append(f"{path.name}:{node.lineno}: .{node.attr}")
    return out


def test_scripts_use_only_the_products_public_names():
    """The lab runs on the product's public names (a script needing an internal asks for a public one)."""
    bad = [hit for p in sorted((REPO / "scripts").rglob("*.py")) for hit in private_uses(p)]
    assert not bad, "\n".join(bad)


def checkout_climbs(path: Path, package: Path) -> list[str]:
    """``Path(__file__)``-relative paths in ``path`` that climb out of ``package`` (``.parent`` chains and
    ``parents[k]``), i.e. into the checkout around an editable install (or site-packages around a wheel)."""
    depth = len(path.relative_to(package).parts)  # .parent climbs this many times to leave the package
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        climbs, inner = 0, node
        while True:
            if isinstance(inner, ast.Attribute) and inner.attr == "parent":
                climbs, inner = climbs + 1, inner.value
            elif isinstance(inner, ast.Subscript) and isinstance(inner.value, ast.Attribute) \
                    and inner.value.attr == "parents" and isinstance(inner.slice, ast.Constant):
                climbs, inner = climbs + int(inner.slice.value) + 1, inner.value.value
            elif isinstance(inner, ast.Call) and isinstance(inner.func, ast.Attribute) and inner.func.attr == "resolve":
                inner = inner.func.value
            else:
                break
        if climbs and "__file__" in ast.unparse(inner) and climbs >= depth + 1:
            out.append(f"{path.relative_to(package.parent)}:{node.lineno}: {ast.unparse(node)}")
    return out


# the one climb kept: an editable install's Hydra configs are the checkout's conf/ (a wheel carries nrc/conf/)
CLIMBS_ALLOWED = {"nrc/config.py: Path(__file__).resolve().parent.parent"}


def test_the_product_never_locates_the_checkout():
    """Default folders come from the working directory, a config key or an environment variable, never from where
    the package's files lie (a wheel's files lie in site-packages)."""
    hits = [h for p in sorted((REPO / "nrc").rglob("*.py")) for h in checkout_climbs(p, REPO / "nrc")]
    bad = [h for h in hits if re.sub(r":\d+:", ":", h) not in CLIMBS_ALLOWED]
    assert not bad, "\n".join(bad)
    assert {re.sub(r":\d+:", ":", h) for h in hits} == CLIMBS_ALLOWED  # the allowance is still needed


def test_the_guards_can_fail(tmp_path):
    """The three scans above see what they forbid."""
    pkg = tmp_path / "nrc"
    (pkg / "evaluation").mkdir(parents=True)
    climb = pkg / "evaluation" / "reference.py"
    climb.write_text("from pathlib import Path\nA = Path(__file__).resolve().parents[2] / 'data'\n"
                     "B = Path(__file__).resolve().parents[1]\nC = Path(__file__).parent.parent.parent\n")
    assert sorted(h.split(":")[1] for h in checkout_climbs(climb, pkg)) == ["2", "4"]
    script = tmp_path / "tool.py"
    script.write_text("from nrc.render.pt import _x\nfrom lab import render\nimport scripts.lab\n"
                      "pt._wavefront(1)\nobj.__dict__\n_own = 1\n")
    assert [h.split(":")[1] for h in private_uses(script)] == ["1", "4"]
    assert lab_imports(script) == ["lab", "scripts.lab"]
