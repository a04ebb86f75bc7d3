"""House rules checked over the source tree.

Three families of checks, each cheap (no pvcmf import, only the files and their syntax trees):

* wording: the tracked text files speak of the product only, never of how it was made
  (see the pattern list below);
* size: every module of ``pvcmf/`` (and every benchmark and gallery script) stays under
  600 lines and every function of ``pvcmf/`` under 100 lines
  of code (docstring, comments and blank lines excluded);
* layers: the package's modules import only from their own or lower layers, and never in a
  cycle (top-level and function-level imports both count).
"""

import ast
import io
import re
import subprocess
import tokenize
from collections import defaultdict
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "pvcmf"
THIS = Path(__file__).resolve()

MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 100

# house-patterns: begin
# the forbidden words are spelled in pieces, so that this file does not use them itself
_W_S, _W_L, _W_E = "sess" + "ion", "le" + "ad", "engin" + "eer"
_W_H, _W_I, _W_LOAD = "hel" + "per", "iss" + "ue", "lo" + "ad"
_W_HASH = "a1a" + "9675"
WORDING = {
    _W_S: re.compile(rf"\b{_W_S}s?\b", re.I),
    f"the {_W_L}": re.compile(rf"\b(?:the|a|our) {_W_L}\b(?!\s+(?:to|time)\b)|\b{_W_L}'s\b", re.I),
    "helper letter": re.compile(r"\bhelpers? [A-D]\b"),
    _W_E: re.compile(rf"\b{_W_E}s?\b", re.I),
    "integrator": re.compile(r"\bintegrators?\b", re.I),
    "issue number": re.compile(r"(?<![\w&/])#[0-9]{1,4}\b(?![0-9a-fA-F])|\bissues? #?[0-9]+\b", re.I),
    "commit hash": re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])(?:[0-9a-f]{40}|[0-9a-f]{7,12})\b"),
    "machine load": re.compile(r"(?<!converge at )(?<!load step )\bload(?: average)?(?: of)? ?[~≈]?[0-9][0-9.]*(?:-[0-9.]+)?\b(?! ?%)", re.I),
}
ALLOWED = [
    re.compile(r"""scope\s*=\s*["']session["']"""),  # pytest fixtures
    re.compile(r"\bsession(?:-scoped| fixtures?)\b", re.I),  # pytest's own terms
]
# house-patterns: end

# Layers, lowest first: a module may import from its own layer and the ones below it only.
LAYERS = [
    ("model", ("pvcmf.arrays", "pvcmf.progress", "pvcmf.run_warnings", "pvcmf._atomic",
               "pvcmf.cache", "pvcmf._version", "pvcmf.plan", "pvcmf.tps",
               "pvcmf.mtm.materials")),
    ("io/datasets/atlas", ("pvcmf.io", "pvcmf.datasets", "pvcmf.atlas")),
    ("filters", ("pvcmf.filters",)),
    ("mtm", ("pvcmf.mtm",)),
    # figures of one case and the run's output files: what the pipeline writes
    ("case figures/outputs", ("pvcmf.figures", "pvcmf.outputs")),
    ("pipeline", ("pvcmf.pipeline", "pvcmf.scan_steps")),
    ("truth/study", ("pvcmf.truth", "pvcmf.study", "pvcmf.reference", "pvcmf.postop",
                     "pvcmf.validation", "pvcmf.sweeps")),
    # figures of a study (sweeps, validation) and the report that shows them
    ("study figures/report", ("pvcmf.figures.parameter_studies", "pvcmf.figures.validation",
                              "pvcmf.report")),
    ("planner/cli/accessor", ("pvcmf.planner", "pvcmf.cli", "pvcmf.accessor", "pvcmf")),
]
# the truth judges the pipeline's predictions, so it never imports the pipeline
TRUTH = ("pvcmf.truth", "pvcmf.reference", "pvcmf.postop")


def _tracked_files():
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True,
                             check=True).stdout
    except (OSError, subprocess.CalledProcessError) as exc:
        pytest.skip(f"not a git checkout ({exc}): the wording check reads `git ls-files`")
    return [ROOT / name for name in out.decode().split("\0") if name]


def _text(path):
    """The file's text, or None for binary and missing files."""
    try:
        data = path.read_bytes()
    except OSError:
        return None
    if b"\0" in data[:8192]:
        return None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return None


def wording_hits(text):
    """(line number, rule, matched text) of every forbidden word in ``text``."""
    hits = []
    skipping = False
    for number, line in enumerate(text.splitlines(), 1):
        if "house-patterns: begin" in line:
            skipping = True
        if skipping:
            skipping = "house-patterns: end" not in line
            continue
        for allowed in ALLOWED:
            line = allowed.sub("", line)
        hits += [(number, rule, m.group(0)) for rule, pattern in WORDING.items()
                 for m in pattern.finditer(line)]
    return hits


# house-patterns: begin (examples of what the patterns must catch)
@pytest.mark.parametrize("text, rule", [
    (f"as the {_W_L} measured", f"the {_W_L}"), (f"in {_W_S} 2", _W_S),
    (f"{_W_H} B wrote", f"{_W_H} letter"), (f"five {_W_E}s", _W_E),
    ("see #" + "12 for", f"{_W_I} number"), (f"fixes {_W_I} 14", f"{_W_I} number"),
    (f"before {_W_HASH} landed", "commit hash"), (f"at {_W_LOAD} 1.6", f"machine {_W_LOAD}"),
    (f"at {_W_LOAD} average 9-12", f"machine {_W_LOAD}"),
    ("commit 4683baa1c2d3e4f5a6b7c8d9e0f1a2b3c4d5e6f7", "commit hash"),
])
# house-patterns: end
def test_wording_patterns_catch(text, rule):
    assert rule in {r for _, r, _ in wording_hits(text)}


@pytest.mark.parametrize("text", [
    '@pytest.fixture(scope="' + _W_S + '")', f"a {_W_S}-scoped fixture", "this may lead to errors", "color='#1f77b4'",
    f"{_W_LOAD} 90 % of the steps", "e = 1e-13", "a sha256 of 64 hex digits " + "ab12" * 16,
    "patients 1-4", "the mtm_helpers module", "the mesh has 30000 tetrahedra",
])
def test_wording_patterns_spare(text):
    assert wording_hits(text) == []


def test_tracked_files_speak_of_the_product_only():
    hits = []
    for path in _tracked_files():
        text = _text(path)
        if text is None:
            continue
        rel = path.relative_to(ROOT)
        hits += [f"{rel}:{n}: {rule}: {found!r}" for n, rule, found in wording_hits(text)]
    assert not hits, (f"{len(hits)} words about how the project was made (say what the code "
                      "does and measures, not its history):\n" + "\n".join(hits[:200]))


def _modules():
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        yield ".".join(parts), path


def test_modules_are_short():
    long = [f"{path.relative_to(ROOT)}: {n} lines" for _, path in _modules()
            if (n := len(path.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES]
    assert not long, f"modules over {MAX_MODULE_LINES} lines (split them):\n" + "\n".join(long)


def test_scripts_are_short():
    """The benchmark and gallery scripts follow the same module size as the package."""
    paths = sorted((ROOT / "benchmarks").glob("*.py")) + sorted((ROOT / "gallery").glob("*.py"))
    assert paths
    long = [f"{path.relative_to(ROOT)}: {n} lines" for path in paths
            if (n := len(path.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES]
    assert not long, f"scripts over {MAX_MODULE_LINES} lines (split them):\n" + "\n".join(long)


def _code_lines(source):
    """Line numbers that hold code (not blank, not only a comment)."""
    lines = set()
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type not in (tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT,
                            tokenize.DEDENT, tokenize.ENDMARKER):
            lines.update(range(tok.start[0], tok.end[0] + 1))
    return lines


def function_lengths(source):
    """(name, first line, code lines) of every function in ``source``, docstrings excluded."""
    code = _code_lines(source)
    out = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        start = min([node.lineno] + [d.lineno for d in node.decorator_list])
        span = set(range(start, node.end_lineno + 1))
        body = node.body
        if (body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant)
                and isinstance(body[0].value.value, str)):
            span -= set(range(body[0].lineno, body[0].end_lineno + 1))
        out.append((node.name, node.lineno, len(span & code)))
    return out


def test_function_length_counts_code_only():
    src = 'def f(x):\n    """Doc.\n\n    More doc.\n    """\n    # a comment\n\n    y = (x +\n         1)\n    return y\n'
    assert function_lengths(src) == [("f", 1, 4)]


def test_functions_are_short():
    long = []
    for _, path in _modules():
        for name, line, n in function_lengths(path.read_text(encoding="utf-8")):
            if n > MAX_FUNCTION_LINES:
                long.append(f"{path.relative_to(ROOT)}:{line} {name}(): {n} code lines")
    assert not long, (f"functions over {MAX_FUNCTION_LINES} code lines (split them):\n"
                      + "\n".join(long))


def layer_of(module):
    """Index in LAYERS of the most specific prefix naming ``module``, or None."""
    best, best_len = None, -1
    for index, (_, prefixes) in enumerate(LAYERS):
        for prefix in prefixes:
            if (module == prefix or module.startswith(prefix + ".")) and len(prefix) > best_len:
                best, best_len = index, len(prefix)
    return best


def _resolve(name, known):
    """The most specific known module that an imported dotted name refers to."""
    while name and name not in known:
        name = name.rpartition(".")[0]
    return name or None


def import_graph():
    """{module: {imported pvcmf module: first line}} over top-level and nested imports."""
    modules = dict(_modules())
    graph = {}
    for module, path in modules.items():
        is_package = path.name == "__init__.py"
        edges = {}
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = []
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = module.split(".")
                    anchor = anchor[:len(anchor) - node.level + (1 if is_package else 0)]
                    base = ".".join(anchor + ([base] if base else []))
                names = [f"{base}.{alias.name}" for alias in node.names] or [base]
            for name in names:
                if name == "pvcmf" or name.startswith("pvcmf."):
                    target = _resolve(name, modules)
                    if target and target != module:
                        edges.setdefault(target, node.lineno)
        graph[module] = edges
    return graph


def test_every_module_has_a_layer():
    missing = [m for m, _ in _modules() if layer_of(m) is None]
    assert not missing, f"modules missing from the layer table in {THIS.name}: {missing}"


def test_imports_only_go_down_the_layers():
    wrong = []
    for module, edges in import_graph().items():
        mine = layer_of(module)
        for target, line in edges.items():
            theirs = layer_of(target)
            if mine is None or theirs is None:
                continue
            if theirs > mine:
                wrong.append(f"{module}:{line} ({LAYERS[mine][0]}) imports {target} "
                             f"({LAYERS[theirs][0]})")
            if (layer_of(module) == layer_of("pvcmf.truth") and module.startswith(TRUTH)
                    and target.startswith("pvcmf.pipeline")):
                wrong.append(f"{module}:{line}: the truth imports the pipeline it judges")
    assert not wrong, "imports from a higher layer:\n" + "\n".join(sorted(wrong))


def find_cycles(graph):
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return cycles


def test_cycle_finder_finds_cycles():
    assert find_cycles({"a": {"b": 1}, "b": {"c": 1}, "c": {"a": 1}, "d": {"a": 1}}) == [
        ["a", "b", "c"]]
    assert find_cycles({"a": {"b": 1}, "b": {}}) == []


def test_no_import_cycles():
    graph = import_graph()
    cycles = find_cycles(graph)
    detail = []
    for component in cycles:
        members = set(component)
        detail.append(" <-> ".join(component) + ": " + ", ".join(
            f"{m}:{line} -> {t}" for m in component for t, line in graph[m].items()
            if t in members))
    assert not cycles, "import cycles among pvcmf modules:\n" + "\n".join(detail)
