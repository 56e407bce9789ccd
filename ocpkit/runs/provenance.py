"""What computed a study trial: the code it runs and the versions of the numerical libraries under it.

A trial's **manifest** names the source files the trial may execute, each with a hash of its bytes, and the
versions of :data:`DEPENDENCIES`. Its files are

* the module defining the trial function and, following ``import`` statements (at any depth, inside functions
  too), every module of ocpkit, of the trial's own top-level package and of the user's own code (a file outside
  the standard library and site-packages) that it imports. A package that imports its submodules by computed name
  (``import_module(f"ocpkit.solvers.{name}")``) counts all of them when it is itself imported by name (``from
  ocpkit import solvers``), not when it is only the folder of a module (``ocpkit.studies`` of
  ``ocpkit.studies.closed_loop``). A module's lazy attributes (PEP 562: the branches ``if name == "X"`` or ``if name
  in (…)`` of its ``__getattr__``, as in ``ocpkit/__init__.py``) count only where they are used: ``from ocpkit
  import LinearMPC``, or ``ocpkit.LinearMPC`` or ``getattr(ocpkit, "LinearMPC")`` after ``import ocpkit``; all of
  them after ``from ocpkit import *`` and where the module is imported as a name of its package (``from pkg import
  sub``, then ``sub.X``, is not traced);
* files named by the trial's parameters: a problem spec ``path/to/file.py:Name`` (and the user modules that file
  imports), ``urdf:robot.urdf``, a ``package.module:Name`` of the user's code.

Other third-party code is neither hashed nor versioned, and a module imported by a name computed at run time
outside those patterns is not seen. A trial's code hash (:func:`manifest_hash`) is a hash of its manifest; the
study runner stores both, so a resumed study can say which modules, versions or variables changed (:func:`changes`).

The manifest also records the **environment variables that change a trial's results** (:func:`environment`), as set
in the process that runs the study, when any is set:

* ``OMP_NUM_THREADS``, ``OPENBLAS_NUM_THREADS``, ``MKL_NUM_THREADS``: the BLAS/OpenMP threads of numpy, CasADi and
  the QP solvers: their measured times, and the order of floating-point sums in multithreaded BLAS calls;
* ``OCPKIT_CPU_THREADS``: Taichi's CPU threads (the sampling planners' times and parallel reductions);
* ``TI_*``: Taichi reads ``TI_<option>`` for any ``ti.init`` option (``TI_ARCH`` picks the CPU or the GPU,
  ``TI_FAST_MATH`` its floating point), except ``TI_OFFLINE_CACHE*`` and ``TI_LOG_LEVEL`` (where compiled kernels are
  kept, how much Taichi says);
* ``CC``: the C compiler of CasADi's JIT and of generated C steps (their floating point and speed).

Not recorded, since they change where files are kept and not what is computed: ``OCPKIT_CACHE_DIR``,
``XDG_CACHE_HOME``, ``TI_OFFLINE_CACHE_FILE_PATH``. Nor are the thread counts the study runner gives its local
worker processes where the user set none (from ``--workers`` and the cores, like the machine itself). A Dask worker
is checked for the manifest's code and versions, not for its environment: Dask's nanny sets the BLAS threads of its
workers to 1 itself, and the trial records the submitting process's variables.

Hashing reads and parses each file once per process, and again only when its size, inode or times change; the
study runner computes a manifest once per run (once per distinct set of files the trials' parameters name).
"""

from __future__ import annotations

import ast
import functools
import hashlib
import importlib.util
import json
import os
import re
import site
import sys
import sysconfig
from collections.abc import Mapping
from importlib import metadata

from ocpkit import __version__

# The numerical libraries whose version is part of every manifest (distribution names, as pip knows them).
DEPENDENCIES = ("casadi", "numpy", "scipy", "proxsuite", "osqp", "daqp", "pin", "taichi", "control")

# Environment variables that change a trial's results (see the module docstring): these names, and those that begin
# with one of the prefixes other than the ones that do not.
ENVIRONMENT = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OCPKIT_CPU_THREADS", "CC")
ENVIRONMENT_PREFIXES = ("TI_",)
NOT_RESULTS = ("TI_OFFLINE_CACHE", "TI_LOG_LEVEL")  # prefixes of variables that change no result

_FILES: dict[str, tuple] = {}  # path -> (stat signature, digest, import references)


def package_version() -> str:
    """The ocpkit version running (``ocpkit.__version__``, which the package metadata is built from)."""
    return __version__


@functools.cache
def dependency_versions() -> dict[str, str | None]:
    """{distribution: installed version, None when not installed} for :data:`DEPENDENCIES` (read once per process)."""
    versions = {}
    for name in DEPENDENCIES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def environment() -> dict[str, str]:
    """{name: value} of the environment variables set in this process that change a trial's results (see the
    module docstring), sorted by name."""
    return {
        name: value
        for name, value in sorted(os.environ.items())
        if (name in ENVIRONMENT or name.startswith(ENVIRONMENT_PREFIXES)) and not name.startswith(NOT_RESULTS)
    }


def manifest(fn, params: Mapping | None = None, variables: Mapping | None = None) -> dict:
    """The manifest of trial function ``fn`` run with ``params``:
    ``{"code": {module name or file as named in params: sha256[:16]}, "dependencies": {name: version}}``, and
    ``"environment": {name: value}`` when :func:`environment` (or ``variables``, given instead) is not empty."""
    return _manifest(fn, _param_references(params or {}, {}), variables)


def manifests(fn, trials) -> list[tuple[str, dict]]:
    """(code hash, manifest) of each parameter dict of ``trials``: one manifest per distinct set of files and
    modules the parameters name, each file read once."""
    seen, by_refs, out = {}, {}, []
    for params in trials:
        refs = _param_references(params, seen)
        if refs not in by_refs:
            m = _manifest(fn, refs)
            by_refs[refs] = (manifest_hash(m), m)
        out.append(by_refs[refs])
    return out


def _manifest(fn, refs: tuple, variables: Mapping | None = None) -> dict:
    name = getattr(fn, "__module__", None) or ""
    walk = _Walk(name.partition(".")[0])
    path = _locate(name) if name else None
    if path is not None:
        walk.visit(name, name, path, explicit=True)
        if "." in name:
            walk.module(name.rpartition(".")[0], explicit=False)
    else:  # no source file to hash (a function built at run time): its bytecode stands in for it
        code = getattr(fn, "__code__", None)
        data = code.co_code + repr(code.co_consts).encode() if code is not None else repr(fn).encode()
        walk.code[getattr(fn, "__qualname__", repr(fn))] = hashlib.sha256(data).hexdigest()[:16]
    for kind, target in refs:
        if kind == "file":
            walk.visit(target, None, target, explicit=True)
        else:
            walk.module(target, explicit=True)
    variables = environment() if variables is None else dict(sorted(variables.items()))
    # Left out when empty: the code hash of a trial run with none set is the one stored before it was recorded.
    return {
        "code": dict(sorted(walk.code.items())),
        "dependencies": dict(dependency_versions()),
        **({"environment": variables} if variables else {}),
    }


def _param_references(params: Mapping, seen: dict) -> tuple:
    """The sorted ("file", path) and ("module", name) references of a trial's parameter strings (``seen`` caches
    them by string within one call)."""
    refs = set()
    for text in _strings(params):
        if text not in seen:
            seen[text] = _references(text)
        refs.update(seen[text])
    return tuple(sorted(refs))


def manifest_hash(manifest: Mapping) -> str:
    """The code hash of a trial: a hash of its manifest (16 hex digits)."""
    return hashlib.sha256(json.dumps(manifest, sort_keys=True, separators=(",", ":")).encode()).hexdigest()[:16]


def changes(old: Mapping | None, new: Mapping) -> list[str]:
    """What differs from manifest ``old`` to ``new``, as phrases naming the modules, files, versions and environment
    variables (one phrase saying so when ``old`` is None: trials stored before manifests were kept)."""
    if old is None:
        return [
            "code recorded before ocpkit 0.2.0 or by another program, without the list of its files, so what "
            "changed is unknown"
        ]
    phrases = []
    was, now = old.get("code", {}), new.get("code", {})
    for verb, names in (
        ("changed", [k for k in was if k in now and was[k] != now[k]]),
        ("now also runs", [k for k in now if k not in was]),
        ("no longer runs", [k for k in was if k not in now]),
    ):
        if names:
            names = sorted(names)
            phrases.append(f"{verb} {', '.join(names[:8])}" + (f" and {len(names) - 8} more" if len(names) > 8 else ""))
    for key, absent in (("dependencies", "not installed"), ("environment", "unset")):
        was, now = old.get(key, {}), new.get(key, {})
        for name in [*now, *(k for k in was if k not in now)]:
            if was.get(name) != now.get(name):
                phrases.append(f"{name} {_shown(was.get(name), absent)} → {_shown(now.get(name), absent)}")
    return phrases


def _shown(value: str | None, absent: str) -> str:
    """A version or variable's value as a change names it: ``absent`` where there is none, quoted where empty."""
    return absent if value is None else value or "''"


class _Walk:
    """Source files reached from the roots through their imports: ``code`` maps each one's label to its digest."""

    def __init__(self, package: str):
        self.package = package  # the trial's top-level package: followed even when installed
        self.code: dict[str, str] = {}
        self.seen: dict[str, bool] = {}  # path -> reached as an explicitly imported module
        self.lazy: dict[str, tuple] = {}  # module -> (a package?, [(attribute names, import reference)])
        self.used: dict[str, set] = {}  # module -> the names of its attributes used ("*": any)

    def module(self, name: str, explicit: bool) -> None:
        """Module ``name`` and its parent packages (importing a.b.c runs a/__init__.py and a/b/__init__.py)."""
        path = _locate(name)
        if path is None or not (_followed(name, path) or (self.package and name.partition(".")[0] == self.package)):
            return
        if "." in name:
            self.module(name.rpartition(".")[0], explicit=False)
        self.visit(name, name, path, explicit)

    def visit(self, label: str, name: str | None, path: str, explicit: bool) -> None:
        """The file ``path`` (module ``name``, None for a file loaded by path) and what it imports."""
        key = os.path.abspath(path)
        if key in self.seen and (self.seen[key] or not explicit):
            return
        again = key in self.seen
        self.seen[key] = explicit
        digest, refs = _read(path)
        if not again:
            self.code[label] = digest
        package = os.path.basename(path) == "__init__.py"
        lazy = [ref[1:] for ref in refs if ref[0] == "lazy"]
        if name is not None and lazy and not again:
            self.lazy[name] = (package, lazy)
            self.attributes(name, self.used.get(name, set()))  # used before the walk reached it
        for ref in refs:
            if ref[0] in ("import", "from", "attribute") and not again:
                self.follow(name, package, ref)
            elif ref[0] == "dynamic" and explicit:  # import_module(f"pkg.{name}"): any submodule of pkg
                for sub in _submodules(ref[1]):
                    self.module(sub, explicit=True)

    def follow(self, name: str | None, package: bool, ref: tuple) -> None:
        """An import reference of module ``name`` (``package``: its file is an ``__init__.py``)."""
        if ref[0] == "import":
            self.module(ref[1], explicit=True)
        elif ref[0] == "attribute":  # ("attribute", module, name): module.name where an import binds module
            self.attributes(ref[1], {ref[2]})
        else:
            base = _absolute(name, package, ref[1], ref[2])
            base_path = _locate(base) if base is not None else None
            if base_path is None or not (_followed(base, base_path) or base.partition(".")[0] == self.package):
                return
            submodules = [f"{base}.{n}" for n in ref[3] if n != "*" and _locate(f"{base}.{n}")]
            self.module(base, explicit=len(submodules) < len(ref[3]))  # an attribute of base is used
            self.attributes(base, set(ref[3]))
            for sub in submodules:
                self.module(sub, explicit=True)
                self.attributes(sub, {"*"})  # bound to a name whose attributes are not traced

    def attributes(self, module: str, names: set) -> None:
        """What ``module``'s lazy attributes ``names`` import ("*": all of them): now if the walk has reached
        ``module``, else when it does."""
        self.used.setdefault(module, set()).update(names)
        package, lazy = self.lazy.get(module, (False, ()))
        for keys, ref in lazy:
            if "*" in names or names.intersection(keys):
                self.follow(module, package, ref)


def _read(path: str) -> tuple[str, tuple]:
    """(sha256[:16] of the file's bytes, its import references), cached until the file's stat changes."""
    try:
        st = os.stat(path)
        signature = (st.st_mtime_ns, st.st_size, st.st_ino, st.st_ctime_ns)
    except OSError:
        return "missing", ()
    key = os.path.abspath(path)
    cached = _FILES.get(key)
    if cached is not None and cached[0] == signature:
        return cached[1], cached[2]
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError:
        return "unreadable", ()
    refs = _imports(data) if path.endswith(".py") else ()
    _FILES[key] = (signature, hashlib.sha256(data).hexdigest()[:16], refs)
    return _FILES[key][1], refs


def _imports(source: bytes) -> tuple:
    """("import", name), ("from", level, module, names), ("dynamic", package), ("lazy", attribute names, one of
    those imports: the branch of a module's ``__getattr__`` for those names) and ("attribute", module, name)
    references of a Python source."""
    try:
        tree = ast.parse(source)
    except (SyntaxError, ValueError):
        return ()  # the trial fails on it; its digest still records it
    refs, bound = [], {}  # bound: {name: the module an import statement binds it to}
    for node, names in _statements(tree.body, module=True):
        if isinstance(node, ast.Import):
            found = [("import", alias.name) for alias in node.names]
            for alias in node.names:
                top = alias.name.partition(".")[0]
                if top not in sys.stdlib_module_names:  # the standard library's modules have no lazy attributes
                    bound[alias.asname or top] = alias.name if alias.asname else top
        elif isinstance(node, ast.ImportFrom):
            found = [("from", node.level, node.module or "", tuple(alias.name for alias in node.names))]
        else:
            continue
        refs.extend(found if names is None else (("lazy", names, ref) for ref in found))
    if b"import_module" in source or b"__import__" in source:  # walking every expression is the slow part
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and node.args and _is_import_call(node.func):
                arg = node.args[0]
                if isinstance(arg, ast.Constant) and isinstance(arg.value, str) and not arg.value.startswith("."):
                    refs.append(("import", arg.value))
                elif isinstance(arg, ast.JoinedStr) and arg.values and isinstance(arg.values[0], ast.Constant):
                    prefix = str(arg.values[0].value)
                    if prefix.endswith(".") and not prefix.startswith("."):
                        refs.append(("dynamic", prefix[:-1]))
    return tuple(refs + _attributes(source, bound))


def _statements(body, names: tuple | None = None, module: bool = False, parameter: str | None = None):
    """(statement, names) for every statement in ``body``, nested ones (in functions, classes, if/try/with/for/match
    blocks) too. ``names`` is None, or for a statement that runs only for some attributes of the module (PEP 562:
    the branch ``if name == "X"`` or ``if name in ("X", …)`` of a module-level ``__getattr__``) their names."""
    for node in body:
        yield node, names
        if module and isinstance(node, ast.FunctionDef) and node.name == "__getattr__" and node.args.args:
            yield from _statements(node.body, parameter=node.args.args[0].arg)
            continue
        keys = _attribute_test(node.test, parameter) if isinstance(node, ast.If) and names is None else None
        if keys:
            yield from _statements(node.body, keys, parameter=parameter)
            yield from _statements(node.orelse, names, parameter=parameter)
            continue
        for field in ("body", "orelse", "finalbody", "handlers", "cases"):
            children = getattr(node, field, None)
            if isinstance(children, list):
                yield from _statements(children, names, parameter=parameter)


def _attribute_test(test, parameter: str | None) -> tuple | None:
    """The names that ``test`` (``parameter == "X"``, ``"X" == parameter`` or ``parameter in ("X", …)``) accepts."""
    if parameter is None or not isinstance(test, ast.Compare) or len(test.ops) != 1:
        return None
    left, op, right = test.left, test.ops[0], test.comparators[0]
    if isinstance(op, ast.Eq) and isinstance(right, ast.Name):
        left, right = right, left
    if not (isinstance(left, ast.Name) and left.id == parameter):
        return None
    if isinstance(op, ast.Eq):
        values = [right]
    elif isinstance(op, ast.In) and isinstance(right, (ast.Tuple, ast.List, ast.Set)):
        values = right.elts
    else:
        return None
    if values and all(isinstance(v, ast.Constant) and isinstance(v.value, str) for v in values):
        return tuple(v.value for v in values)
    return None


def _attributes(source: bytes, bound: dict) -> list:
    """("attribute", module, name), sorted, for each ``module.name`` and ``getattr(module, "name")`` in ``source``
    where ``module`` is bound by an import statement (``a.b.c``: a's b and a.b's c). The text is searched, not the
    syntax tree (ten times faster): a comment or a string that reads so, or ``x.module.name``, counts too."""
    if not bound:
        return []
    text, names = source.decode(errors="replace"), "|".join(map(re.escape, bound))
    chains = set(re.findall(rf"\b({names})((?:\s*\.\s*\w+)+)", text))
    chains.update(
        (root, "." + name)
        for root, name in re.findall(rf"\b(?:getattr|hasattr)\(\s*({names})\s*,\s*['\"](\w+)['\"]", text)
    )
    found = set()
    for root, chain in chains:
        module = bound[root]
        for name in chain.split(".")[1:]:
            found.add(("attribute", module, name.strip()))
            module = f"{module}.{name.strip()}"
    return sorted(found)


def _is_import_call(func) -> bool:
    name = func.id if isinstance(func, ast.Name) else func.attr if isinstance(func, ast.Attribute) else None
    return name in ("import_module", "__import__")


def _absolute(name: str | None, package: bool, level: int, module: str) -> str | None:
    """The absolute module of ``from <level dots><module> import …`` in module ``name``."""
    if not level:
        return module or None
    if not name or name == "__main__":
        return None
    parts = name.split(".") if package else name.split(".")[:-1]
    if level - 1 > len(parts) or (level - 1 == len(parts) and not module):
        return None
    parts = parts[: len(parts) - (level - 1)]
    return ".".join(parts + ([module] if module else [])) or None


def _locate(name: str) -> str | None:
    """The source file of module ``name``, found without importing anything new (None if there is none)."""
    module = sys.modules.get(name)
    if module is not None:
        path = getattr(module, "__file__", None)
        return path if path and os.path.isfile(path) else None
    parent, _, child = name.rpartition(".")
    if not parent:
        try:
            spec = importlib.util.find_spec(name)
        except (ImportError, ValueError):
            return None
        return spec.origin if spec is not None and spec.has_location and os.path.isfile(spec.origin) else None
    parent_path = _locate(parent)
    if parent_path is None or os.path.basename(parent_path) != "__init__.py":
        return None
    for folder in _package_dirs(parent, parent_path):
        for path in (os.path.join(folder, child + ".py"), os.path.join(folder, child, "__init__.py")):
            if os.path.isfile(path):
                return path
    if parent in sys.modules:  # a subpackage mapped elsewhere (an editable install's package-dir); nothing runs
        try:
            spec = importlib.util.find_spec(name)
        except (ImportError, ValueError):
            return None
        return spec.origin if spec is not None and spec.has_location and os.path.isfile(spec.origin) else None
    return None


def _package_dirs(name: str, init_path: str) -> list[str]:
    return list(getattr(sys.modules.get(name), "__path__", None) or [os.path.dirname(init_path)])


def _submodules(package: str) -> list[str]:
    """The modules and subpackages directly inside ``package``."""
    path = _locate(package)
    if path is None or os.path.basename(path) != "__init__.py":
        return []
    names = set()
    for folder in _package_dirs(package, path):
        try:
            entries = os.listdir(folder)
        except OSError:
            continue
        for entry in entries:
            if entry.endswith(".py") and entry != "__init__.py" and entry[:-3].isidentifier():
                names.add(f"{package}.{entry[:-3]}")
            elif entry.isidentifier() and os.path.isfile(os.path.join(folder, entry, "__init__.py")):
                names.add(f"{package}.{entry}")
    return sorted(names)


def _followed(name: str, path: str) -> bool:
    """ocpkit's modules and the user's: not the standard library's or an installed package's."""
    if name == "ocpkit" or name.startswith("ocpkit."):
        return True
    real = os.path.realpath(path)
    return not any(real.startswith(folder) for folder in _library_dirs())


@functools.cache
def _library_dirs() -> tuple[str, ...]:
    folders = {
        path for key, path in sysconfig.get_paths().items() if key in ("stdlib", "platstdlib", "purelib", "platlib")
    }
    folders.update(getattr(site, "getsitepackages", list)())
    folders.add(site.getusersitepackages() or "")
    return tuple(os.path.join(os.path.realpath(f), "") for f in folders if f)


def _strings(value):
    """The strings inside parameters (values of nested dicts and lists)."""
    if isinstance(value, str):
        yield value
    elif isinstance(value, Mapping):
        for item in value.values():
            yield from _strings(item)
    elif isinstance(value, (list, tuple)):
        for item in value:
            yield from _strings(item)


def _references(text: str) -> tuple:
    """("file", path) and ("module", name) a parameter string names: ``file.py:Name``, ``urdf:robot.urdf``, a file
    path, ``package.module:Name`` (one that resolves to the user's code)."""
    found = []
    if ".py:" in text:
        path = text.rpartition(".py:")[0] + ".py"
        if os.path.isfile(path):
            found.append(("file", path))
        return tuple(found)
    for candidate in (text, text.partition(":")[2]):
        if candidate and ("/" in candidate or "." in os.path.basename(candidate)) and os.path.isfile(candidate):
            found.append(("file", candidate))
            break
    module = text.partition(":")[0]
    if ":" in text and module and all(part.isidentifier() for part in module.split(".")):
        path = _locate(module)
        if path is not None and _followed(module, path):
            found.append(("module", module))
    return tuple(found)
