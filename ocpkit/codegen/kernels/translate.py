"""CasADi SX Function -> Taichi ``@ti.func``, by walking the Function's instruction list.

The EMPC kernel (paper, Section "Evolutionary MPC") must simulate exactly the dynamics and
costs the QPs and IPOPT use, so those CasADi Functions are translated rather than rewritten.
Taichi compiles from inspectable source, so the translation is written to a cache file
keyed by a hash of the Function's serialization and imported from there, once its text is
checked against a fresh translation.

Calling convention of the generated function: every input is passed densely as a Taichi
vector of its entries in column-major order (structural zeros included), and every output
comes back the same way; a Function with several outputs returns a tuple of vectors.
"""

from __future__ import annotations

import hashlib
import importlib.util
import sys
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from ocpkit.codegen.cache import cache_dir as shared_cache_dir
from ocpkit.codegen.cache import check_trusted, read_only, write_atomically
from ocpkit.codegen.kernels import runtime

# Bumped whenever the generated text changes, so stale cache files are never imported.
_GENERATOR_VERSION = "3"

_OP_NAMES = {getattr(ca, name): name for name in dir(ca) if name.startswith("OP_")}

# Operation -> Taichi expression template over the instruction's inputs {0}, {1}.
# Comparisons and logic yield 1.0/0.0 in the Function's float type, as CasADi does.
_EXPRESSIONS = {
    ca.OP_ASSIGN: "{0}",
    ca.OP_ADD: "{0} + {1}",
    ca.OP_SUB: "{0} - {1}",
    ca.OP_MUL: "{0} * {1}",
    ca.OP_DIV: "{0} / {1}",
    ca.OP_NEG: "-{0}",
    ca.OP_TWICE: "{0} + {0}",
    ca.OP_SQ: "{0} * {0}",
    ca.OP_INV: "_F(1.0) / {0}",
    ca.OP_POW: "ti.pow({0}, {1})",
    ca.OP_CONSTPOW: "ti.pow({0}, {1})",
    ca.OP_SQRT: "ti.sqrt({0})",
    ca.OP_EXP: "ti.exp({0})",
    ca.OP_LOG: "ti.log({0})",
    ca.OP_SIN: "ti.sin({0})",
    ca.OP_COS: "ti.cos({0})",
    ca.OP_TAN: "ti.tan({0})",
    ca.OP_ASIN: "ti.asin({0})",
    ca.OP_ACOS: "ti.acos({0})",
    ca.OP_ATAN: "ti.atan2({0}, _F(1.0))",
    ca.OP_ATAN2: "ti.atan2({0}, {1})",
    ca.OP_SINH: "_F(0.5) * (ti.exp({0}) - ti.exp(-{0}))",
    ca.OP_COSH: "_F(0.5) * (ti.exp({0}) + ti.exp(-{0}))",
    ca.OP_TANH: "ti.tanh({0})",
    ca.OP_HYPOT: "ti.sqrt({0} * {0} + {1} * {1})",
    ca.OP_FABS: "ti.abs({0})",
    ca.OP_FLOOR: "ti.floor({0}, _F)",
    ca.OP_CEIL: "ti.ceil({0}, _F)",
    ca.OP_FMIN: "ti.min({0}, {1})",
    ca.OP_FMAX: "ti.max({0}, {1})",
    ca.OP_SIGN: "ti.select({0} < 0, _F(-1.0), ti.select({0} > 0, _F(1.0), {0}))",
    ca.OP_COPYSIGN: "ti.select({1} < 0, -ti.abs({0}), ti.abs({0}))",
    ca.OP_LT: "ti.select({0} < {1}, _F(1.0), _F(0.0))",
    ca.OP_LE: "ti.select({0} <= {1}, _F(1.0), _F(0.0))",
    ca.OP_EQ: "ti.select({0} == {1}, _F(1.0), _F(0.0))",
    ca.OP_NE: "ti.select({0} != {1}, _F(1.0), _F(0.0))",
    ca.OP_NOT: "ti.select({0} == 0, _F(1.0), _F(0.0))",
    ca.OP_AND: "ti.select(({0} != 0) & ({1} != 0), _F(1.0), _F(0.0))",
    ca.OP_OR: "ti.select(({0} != 0) | ({1} != 0), _F(1.0), _F(0.0))",
    ca.OP_IF_ELSE_ZERO: "ti.select({0} != 0, {1}, _F(0.0))",
}

SUPPORTED_OPERATIONS = tuple(sorted(_OP_NAMES[op] for op in _EXPRESSIONS)) + ("OP_CONST", "OP_INPUT", "OP_OUTPUT")

_DTYPES = {"float64": "ti.f64", "float32": "ti.f32"}


def cache_dir() -> Path:
    """Where generated kernels live (see :mod:`ocpkit.codegen.cache`)."""
    return shared_cache_dir("taichi")


@dataclass(frozen=True)
class TaichiFunction:
    """A CasADi Function translated to Taichi.

    ``func`` is the ``@ti.func`` (dense column-major vectors in, dense vectors out);
    ``input_shapes``/``output_shapes`` are the CasADi (rows, cols); ``path`` is the
    generated source file.
    """

    name: str
    func: object
    input_shapes: tuple[tuple[int, int], ...]
    output_shapes: tuple[tuple[int, int], ...]
    precision: str
    path: Path
    _module: object

    def __call__(self, *inputs: np.ndarray) -> tuple[np.ndarray, ...]:
        """Evaluate on a batch in a Taichi kernel: input j has shape (N, rows_j, cols_j)
        (or (N, rows_j) for a column); returns one (N, rows, cols) array per output."""
        if len(inputs) != len(self.input_shapes):
            raise TypeError(f"{self.name}: expected {len(self.input_shapes)} inputs, got {len(inputs)}")
        batch = None
        flat = []
        for j, (value, (rows, cols)) in enumerate(zip(inputs, self.input_shapes)):
            value = np.asarray(value, dtype=np.float64)
            if value.ndim not in (2, 3) or value.shape[1:] not in ((rows, cols), (rows * cols,)):
                raise ValueError(f"{self.name}: input {j} must have shape (N, {rows}, {cols}), got {value.shape}")
            if batch is None:
                batch = value.shape[0]
            if value.shape[0] != batch or batch == 0:
                raise ValueError(f"{self.name}: input {j} has batch size {value.shape[0]}, expected {batch} (> 0)")
            flat.append(value.reshape(batch, rows, cols).transpose(0, 2, 1).reshape(batch, -1))
        ntype = runtime.float_types(self.precision)[1]
        outputs = [np.empty((batch, r * c), dtype=ntype) for r, c in self.output_shapes]
        self._module.batch(*(np.ascontiguousarray(value, dtype=ntype) for value in flat), *outputs)
        return tuple(
            out.astype(np.float64).reshape(batch, c, r).transpose(0, 2, 1)
            for out, (r, c) in zip(outputs, self.output_shapes)
        )


def translate(function: ca.Function, *, precision: str = "float64") -> TaichiFunction:
    """Translate a CasADi SX Function (an MX one is expanded first) into a Taichi function.

    Raises ``TypeError`` if ``function`` is not a CasADi Function or cannot be expanded to SX,
    ``ValueError`` for free variables, empty inputs/outputs, an unknown ``precision``, or an
    operation with no Taichi counterpart (the error names it).
    """
    if not isinstance(function, ca.Function):
        raise TypeError(f"function must be a casadi.Function, got {type(function).__name__}")
    if precision not in _DTYPES:
        raise ValueError(f"precision must be 'float64' or 'float32', got {precision!r}")
    if not function.is_a("SXFunction"):
        try:
            function = function.expand()
        except RuntimeError as exc:
            raise TypeError(f"function {function.name()!r} cannot be expanded to an SX Function: {exc}") from exc
    if function.has_free():
        raise ValueError(f"function {function.name()!r} has free variables {function.free_sx()}; make them inputs")
    if function.n_in() == 0 or function.n_out() == 0:
        raise ValueError(f"function {function.name()!r} needs at least one input and one output")
    runtime.init()
    for kind, count, sparsity in (
        ("input", function.n_in(), function.sparsity_in),
        ("output", function.n_out(), function.sparsity_out),
    ):
        for j in range(count):
            if sparsity(j).numel() == 0:
                raise ValueError(f"function {function.name()!r}: {kind} {j} is empty")
    key = hashlib.sha256(f"{_GENERATOR_VERSION}|{precision}|{function.serialize()}".encode()).hexdigest()[:24]
    path = cache_dir() / f"fn_{key}.py"
    module_name = f"ocpkit_kernel_{key}"
    if module_name not in sys.modules:
        # The cache saves Taichi's compile, not the translation: the text is generated again and the file
        # imported only if it is exactly that text, so a damaged or tampered entry is never executed.
        text = _source(function, precision)
        try:
            cached = path.read_text() if path.exists() else None
        except (OSError, UnicodeDecodeError):
            cached = ""
        if cached != text:
            if cached is not None:
                warnings.warn(
                    f"kernel cache entry {path} differs from its translation (damaged or modified): rewritten",
                    RuntimeWarning,
                    stacklevel=2,
                )
            path = _write_atomically(path, text)
    module = _import(path, module_name)
    return TaichiFunction(
        name=function.name(),
        func=module.evaluate,
        input_shapes=tuple(function.size_in(j) for j in range(function.n_in())),
        output_shapes=tuple(function.size_out(j) for j in range(function.n_out())),
        precision=precision,
        path=path,
        _module=module,
    )


def _source(function: ca.Function, precision: str) -> str:
    """The generated module text: ``evaluate`` (the ti.func) and ``batch`` (a kernel over a batch: tests)."""
    n_in, n_out = function.n_in(), function.n_out()
    in_dense = [function.sparsity_in(j).find() for j in range(n_in)]
    out_dense = [function.sparsity_out(j).find() for j in range(n_out)]
    out_terms = [["_F(0.0)"] * function.sparsity_out(j).numel() for j in range(n_out)]
    body = []
    for k in range(function.n_instructions()):
        op = function.instruction_id(k)
        args = function.instruction_input(k)
        res = function.instruction_output(k)
        if op == ca.OP_CONST:
            body.append(f"w{res[0]} = _F({_literal(function.instruction_constant(k))})")
        elif op == ca.OP_INPUT:
            body.append(f"w{res[0]} = i{args[0]}[{in_dense[args[0]][args[1]]}]")
        elif op == ca.OP_OUTPUT:
            # Work slots are reused later, so each output entry gets its own local.
            name = f"o{res[0]}_{res[1]}"
            body.append(f"{name} = w{args[0]}")
            out_terms[res[0]][out_dense[res[0]][res[1]]] = name
        elif op in _EXPRESSIONS:
            body.append(f"w{res[0]} = " + _EXPRESSIONS[op].format(*(f"w{a}" for a in args)))
        else:
            name = _OP_NAMES.get(op, str(op))
            raise ValueError(
                f"function {function.name()!r}: CasADi operation {name} "
                f"(instruction {k}) has no Taichi translation; supported: "
                f"{', '.join(SUPPORTED_OPERATIONS)}"
            )
    params = ", ".join(f"i{j}" for j in range(n_in))
    arrays = [f"x{j}" for j in range(n_in)] + [f"y{j}" for j in range(n_out)]
    outs = [f"ti.Vector([{', '.join(terms)}], dt=_F)" for terms in out_terms]
    lines = [
        f"# Generated by ocpkit.codegen.kernels.translate from CasADi Function {function.name()!r}.",
        "# Do not edit: regenerated whenever the Function changes.",
        "import taichi as ti",
        "",
        f"_F = {_DTYPES[precision]}",
        "_INF = float('inf')",
        "_NAN = float('nan')",
        "",
        "",
        "@ti.func",
        f"def evaluate({params}):",
        *(f"    {line}" for line in body),
        f"    return {', '.join(outs)}",
        "",
        "",
        "@ti.kernel",
        f"def batch({', '.join(f'{a}: ti.types.ndarray()' for a in arrays)}):",
        "    for s in range(x0.shape[0]):",
    ]
    for j in range(n_in):
        numel = function.sparsity_in(j).numel()
        lines.append(f"        a{j} = ti.Vector([x{j}[s, c] for c in ti.static(range({numel}))], dt=_F)")
    results = ", ".join(f"r{j}" for j in range(n_out))
    lines.append(f"        {results} = evaluate({', '.join(f'a{j}' for j in range(n_in))})")
    for j in range(n_out):
        numel = function.sparsity_out(j).numel()
        lines.append(f"        for c in ti.static(range({numel})):")
        lines.append(f"            y{j}[s, c] = r{j}[c]")
    lines.append("")
    return "\n".join(lines)


def _literal(value: float) -> str:
    if np.isnan(value):
        return "_NAN"
    if np.isinf(value):
        return "_INF" if value > 0 else "-_INF"
    return repr(float(value))  # repr round-trips a double exactly


def _write_atomically(path: Path, text: str) -> Path:
    """Write the generated module (other processes, Dask workers or parallel tests, may generate the same file at
    once); where the cache is read-only or full, into a folder of this process's own instead (the text is regenerated
    every run anyway: nothing is lost but the file). Returns the path written."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        write_atomically(path, text.encode())
    except OSError as exc:
        if not read_only(exc):
            raise
        path = _private_dir() / path.name
        write_atomically(path, text.encode())
    return path


_private = []


def _private_dir() -> Path:
    """A folder of this process's own for generated modules a read-only cache cannot take (removed at exit)."""
    if not _private:
        import atexit
        import shutil

        _private.append(Path(tempfile.mkdtemp(prefix="ocpkit-kernels-")))
        atexit.register(shutil.rmtree, _private[0], True)
    return _private[0]


def _import(path: Path, module_name: str):
    if module_name in sys.modules:
        return sys.modules[module_name]
    spec = importlib.util.spec_from_file_location(module_name, check_trusted(path))
    module = importlib.util.module_from_spec(spec)
    sys.modules[module_name] = module
    spec.loader.exec_module(module)
    return module
