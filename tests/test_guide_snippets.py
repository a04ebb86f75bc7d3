"""Code blocks of the user guide that claim to run as written.

A block meant to be copied into a script must define every name it uses, before it uses
it; the one of the fast plan response (``docs/guide/skin_and_planning.md``) also runs.
"""

import ast
import builtins
import re
from pathlib import Path

import pytest

GUIDE = Path(__file__).resolve().parents[1] / "docs" / "guide"


def _block(page, marker):
    """The python code block of ``page`` that contains ``marker``."""
    text = (GUIDE / page).read_text(encoding="utf-8")
    blocks = [b for b in re.findall(r"```python\n(.*?)```", text, re.S) if marker in b]
    assert len(blocks) == 1, f"{page}: {len(blocks)} python blocks hold {marker!r}"
    return blocks[0]


def _used_before_defined(code):
    """Names a block loads that nothing before them (in source order) binds or imports."""
    defined = set(dir(builtins))
    missing = []
    for stmt in ast.parse(code).body:
        loads = [n.id for n in ast.walk(stmt) if isinstance(n, ast.Name)
                 and isinstance(n.ctx, ast.Load)]
        local = {a.arg for n in ast.walk(stmt) if isinstance(n, ast.Lambda)
                 for a in n.args.args}
        local |= {n.id for n in ast.walk(stmt) if isinstance(n, ast.comprehension)
                  for n in ast.walk(n.target) if isinstance(n, ast.Name)}
        missing += [name for name in loads if name not in defined | local]
        for n in ast.walk(stmt):
            if isinstance(n, (ast.Import, ast.ImportFrom)):
                defined |= {(a.asname or a.name).split(".")[0] for a in n.names}
            elif isinstance(n, ast.Name) and isinstance(n.ctx, ast.Store):
                defined.add(n.id)
    return sorted(set(missing))


def test_plan_response_block_defines_what_it_uses():
    assert _used_before_defined(_block("skin_and_planning.md", "plan_response(")) == []


def test_the_checker_sees_a_name_used_before_it_is_bound():
    assert _used_before_defined("a = b + 1\nb = 2\n") == ["b"]
    assert _used_before_defined("import numpy as np\nx = [i for i in np.arange(3)]\n") == []


@pytest.mark.slow
def test_plan_response_block_runs(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    scope = {}
    exec(compile(_block("skin_and_planning.md", "plan_response("), "guide", "exec"), scope)
    assert scope["lip_u"].shape == (len(scope["plans"]), 1, 3)
    assert scope["skin"].n_points == scope["result"].skin_pre.n_points


ROOT = GUIDE.parents[1]


def _statements(code):
    """The block's statements as normalised source (comments and layout dropped)."""
    return [ast.unparse(s) for s in ast.parse(code).body]


def test_readme_pipeline_is_the_quickstart_and_runs_clean(tmp_path, monkeypatch):
    """The README's pipeline block is ``examples/quickstart.py``'s, statement for statement,
    and the example runs with no warning of a doubtful solution (inverted tetrahedra)."""
    import runpy
    import warnings

    text = (ROOT / "README.md").read_text(encoding="utf-8")
    readme = next(b for b in re.findall(r"```python\n(.*?)```", text, re.S)
                  if "map_to_surface" in b)
    example = (ROOT / "examples" / "quickstart.py").read_text(encoding="utf-8")
    assert set(_statements(readme)) <= set(_statements(example))
    assert not _used_before_defined(readme)
    monkeypatch.chdir(tmp_path)
    from pvcmf.mtm.solver import SolutionWarning

    with warnings.catch_warnings():
        warnings.simplefilter("error", SolutionWarning)
        runpy.run_path(str(ROOT / "examples" / "quickstart.py"), run_name="__main__")
    assert (tmp_path / "quickstart-out" / "predicted_skin.vtp").is_file()
