"""numba started without its BLAS check (core.jit.start_without_blas): the compiled loops work,
scipy.linalg is importable afterwards, and no compiled function needs a BLAS."""

from __future__ import annotations

import ast
import subprocess
import sys
import textwrap
from pathlib import Path

import lidarcal_ros

PACKAGE = Path(lidarcal_ros.__file__).parent

#: What numba compiles through BLAS/LAPACK (or, without one, through a loop of its own that
#: sums in another order): none of it may appear in a compiled function.
BLAS_NAMES = {"dot", "vdot", "matmul", "linalg", "convolve", "correlate"}
COMPILING_DECORATORS = {"compiled", "inlined", "njit", "jit", "vectorize", "guvectorize"}


def _decorator_name(node: ast.expr) -> str:
    if isinstance(node, ast.Call):
        node = node.func
    if isinstance(node, ast.Attribute):
        return node.attr
    return node.id if isinstance(node, ast.Name) else ""


def _compiled_functions() -> list[tuple[Path, ast.FunctionDef]]:
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.FunctionDef) and any(
                    _decorator_name(d) in COMPILING_DECORATORS for d in node.decorator_list):
                found.append((path, node))
    return found


def test_no_compiled_function_needs_blas() -> None:
    functions = _compiled_functions()
    assert len(functions) > 50  # the walk finds the package's kernels
    offenders = []
    for path, func in functions:
        for node in ast.walk(func):
            if isinstance(node, ast.BinOp) and isinstance(node.op, ast.MatMult):
                offenders.append(f"{path.name}:{node.lineno} {func.name}: @")
            elif isinstance(node, ast.Attribute) and node.attr in BLAS_NAMES:
                offenders.append(f"{path.name}:{node.lineno} {func.name}: .{node.attr}")
    assert offenders == []


def test_detector_sees_blas_use() -> None:
    """The check above would catch a kernel that used np.dot or ``@``."""
    source = textwrap.dedent("""
        @compiled
        def f(a, b):
            return np.dot(a, b) + (a @ b)
    """)
    func = ast.parse(source).body[0]
    assert isinstance(func, ast.FunctionDef)
    assert _decorator_name(func.decorator_list[0]) in COMPILING_DECORATORS
    hits = [n for n in ast.walk(func)
            if (isinstance(n, ast.BinOp) and isinstance(n.op, ast.MatMult))
            or (isinstance(n, ast.Attribute) and n.attr in BLAS_NAMES)]
    assert len(hits) == 2


def test_start_without_blas_in_a_fresh_process() -> None:
    script = textwrap.dedent("""
        import sys
        from lidarcal_ros.core.jit import start_without_blas
        start_without_blas()
        assert "scipy.linalg" not in sys.modules, "scipy.linalg was imported"
        import numba.np.arraymath
        assert numba.np.arraymath._HAVE_BLAS is False
        from lidarcal_ros.pipeline.correction.bag import warm_up_compiled_loops
        warm_up_compiled_loops()  # every loop of the correction runs
        import scipy.linalg
        assert float(scipy.linalg.solve([[2.0]], [4.0])[0]) == 2.0
        print("ok")
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "ok"


def test_start_without_blas_after_scipy_linalg() -> None:
    """Where scipy.linalg is imported already, numba keeps its BLAS."""
    script = textwrap.dedent("""
        import scipy.linalg
        from lidarcal_ros.core.jit import start_without_blas
        start_without_blas()
        import numba.np.arraymath
        assert numba.np.arraymath._HAVE_BLAS is True
        print("ok")
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "ok"


def test_start_without_blas_holds_the_compiler_lock() -> None:
    """The registries of numba load under its compiler lock, as its own compilations load them: a
    kernel compiled meanwhile in another thread (the correction's reading thread compiles
    while the warm-up thread starts numba) must not be typed against half-loaded ones."""
    script = textwrap.dedent("""
        from numba.core.compiler_lock import global_compiler_lock
        from numba.core.registry import cpu_target
        from lidarcal_ros.core.jit import start_without_blas
        context = cpu_target.target_context
        held = []
        refresh = type(context).refresh
        type(context).refresh = lambda self: (held.append(global_compiler_lock.is_locked()),
                                              refresh(self))
        start_without_blas()
        assert held and all(held), held
        print("ok")
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "ok"
