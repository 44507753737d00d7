"""Plain pointers for the state rows in an AOTInductor step's C++ wrapper (a build-time rewrite of its text).

A step returns its state as a stack of rows, and Inductor lowers that stack by letting every row's producer write
straight into the stacked buffer: the wrapper declares one tensor view per row (``reinterpret_tensor_wrapper(base,
..., offset)``, marked ``// alias``) only to hand ``view.data_ptr()`` to the step's one fused kernel. Each view is
a heap-allocated tensor made and freed on every call: 156 of them a call in NRC's step (59 float and 16 integer
state rows, input and output), ~0.2 µs each, most of what a call costs at a few live slots
(docs/measurements/nrc_frames.md, "Row views").

:func:`raw_row_views` rewrites each such view into a pointer into its base buffer, ``base + offset`` elements, but
only where that is the same thing: the view is used nowhere but as ``view.data_ptr()``, its base was allocated in
the wrapper with a known element type, and the base is neither moved nor freed before the view's last use. Every
other line is left as Inductor wrote it. :func:`plain_row_views` applies it to the wrapper an ahead-of-time build
compiles (torch 2.13's ``AotCodeCompiler.compile``; with another torch the build runs unchanged).
"""

from __future__ import annotations

import contextlib
import re
from collections.abc import Iterator
from typing import Any

import torch

_ALIAS = re.compile(r"^(?P<indent>\s*)auto (?P<name>buf\d+) = wrap_with_raii_handle_if_needed\("
                    r"reinterpret_tensor_wrapper\((?P<base>buf\d+), \d+, \w+, \w+, (?P<offset>[^;]+?)\)\);"
                    r"\s*// alias$")
_ALLOC = re.compile(r"aoti_torch_empty_strided\(.*cached_torch_dtype_(?P<dtype>\w+), .*&(?P<name>buf\d+)_handle\)")
_POINTER = ("struct NrcRowPointer {  // a state row inside a buffer: all a kernel call takes from a view (nrc)\n"
            "    void* ptr;\n"
            "    void* data_ptr() const { return ptr; }\n"
            "};\n\n")
_RUN, _END = "void AOTInductorModel::run_impl(", "} // AOTInductorModel::run_impl"


def _itemsize(dtype: str | None) -> int | None:
    """Bytes an element of ``cached_torch_dtype_<dtype>`` (``None``: not a torch dtype)."""
    kind = getattr(torch, dtype, None) if dtype else None
    return kind.itemsize if isinstance(kind, torch.dtype) else None


def raw_row_views(code: str) -> tuple[str, int]:
    """``code`` (an AOTInductor C++ wrapper) with the safe row views made pointers, and how many were."""
    start, end = code.find(_RUN), code.find(_END)
    if start < 0 or end < start:
        return code, 0
    head, lines, tail = code[:start], code[start:end].split("\n"), code[end:]  # run_impl's body alone
    dtypes = {m["name"]: m["dtype"] for m in map(_ALLOC.search, lines) if m}
    changed = 0
    for i, line in enumerate(lines):
        m = _ALIAS.match(line)
        size = _itemsize(dtypes.get(m["base"])) if m else None
        if size is None:
            continue
        name, base = m["name"], m["base"]
        uses = [j for j, other in enumerate(lines) if j != i and re.search(rf"\b{name}\b", other)]
        if not uses or any(re.search(rf"\b{name}\b", re.sub(rf"\b{name}\.data_ptr\(\)", "", lines[j]))
                           for j in uses):  # used as anything but a pointer
            continue
        last = max(uses)
        if any(re.search(rf"std::move\({base}\)|\b{base}\.(reset|release)\(\)", lines[j]) for j in range(last + 1)):
            continue
        lines[i] = (f"{m['indent']}NrcRowPointer {name}{{static_cast<char*>({base}.data_ptr()) + "
                    f"({m['offset']}) * {size}}};  // row of {base}")
        changed += 1
    if not changed:
        return code, 0
    return head + _POINTER + "\n".join(lines) + tail, changed


@contextlib.contextmanager
def plain_row_views(report: dict[str, int] | None = None) -> Iterator[None]:
    """Inside the block, ahead-of-time builds compile their wrapper through :func:`raw_row_views` (the count of
    rewritten views summed into ``report["row_views"]``)."""
    try:
        from torch._inductor.codecache import AotCodeCompiler
    except ImportError:  # pragma: no cover -- another torch's layout: build as Inductor writes it
        yield
        return
    original = AotCodeCompiler.__dict__.get("compile")
    if not isinstance(original, classmethod):  # pragma: no cover -- another torch's layout
        yield
        return

    def compile(cls: Any, graph: Any, wrapper_code: str, *args: Any, **kwargs: Any) -> Any:
        wrapper_code, n = raw_row_views(wrapper_code)
        if report is not None:
            report["row_views"] = report.get("row_views", 0) + n
        return original.__func__(cls, graph, wrapper_code, *args, **kwargs)

    AotCodeCompiler.compile = classmethod(compile)  # type: ignore[method-assign]
    try:
        yield
    finally:
        AotCodeCompiler.compile = original  # type: ignore[method-assign]
