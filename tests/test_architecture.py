"""The package's layers (docs/architecture.md): imports only go down, and no script imports another script."""

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
    bad = [f"{p.name} imports {t}" for p in (REPO / "scripts").glob("*.py") for t in imports(p) if t in scripts]
    assert not bad, bad


def test_no_script_edits_sys_path():
    """Scripts import the installed package (``pip install -e .``), never the checkout through ``sys.path``."""
    bad = []
    for p in sorted((REPO / "scripts").glob("*.py")):
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
