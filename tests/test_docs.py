"""The documentation cannot rot: the site builds with warnings as errors, and the code on its pages runs.

- ``test_docs_build`` runs ``sphinx-build -W --keep-going -b html docs <tmp>`` (skipped, saying why, when the
  ``docs`` extra is not installed);
- ``test_tutorial_runs`` executes the ``python`` code blocks of each tutorial in order, in one namespace, from a
  temporary working directory (so nothing is written into the repository);
- ``test_readme_examples`` does the same for the README's quickstart and DQN example and checks what they claim.

Code blocks marked ``bash`` (commands) are shown, not run.
"""
import importlib
import importlib.util
import os
import pathlib
import pkgutil
import re
import subprocess
import sys

import pytest
import torch

ROOT = pathlib.Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
TUTORIALS = sorted((DOCS / "tutorials").glob("*.md"))
_PYTHON_BLOCK = re.compile(r"^```python\n(.*?)^```", re.S | re.M)


def python_blocks(path: pathlib.Path) -> list[str]:
    """The ``python`` fenced code blocks of a Markdown file, in order."""
    return _PYTHON_BLOCK.findall(path.read_text())


def run_blocks(path: pathlib.Path, workdir: pathlib.Path) -> dict:
    """Executes a page's ``python`` blocks in one namespace from ``workdir``; returns the namespace."""
    namespace = {"__name__": f"docs:{path.name}"}
    cwd = os.getcwd()
    os.chdir(workdir)
    try:
        with torch.random.fork_rng():
            for index, code in enumerate(python_blocks(path)):
                exec(compile(code, f"{path.relative_to(ROOT)}[block {index}]", "exec"), namespace)  # noqa: S102
    finally:
        os.chdir(cwd)
    return namespace


def test_every_tutorial_has_code():
    names = {p.stem for p in TUTORIALS}
    assert {"discover_options", "options_in_dqn", "hierarchies", "segmentation"} <= names, names
    for path in TUTORIALS:
        if path.stem != "reproducing_the_paper":  # commands only: the paper's runs take minutes to hours
            assert python_blocks(path), f"{path.name} has no python block to run"


@pytest.mark.parametrize("path", [p for p in TUTORIALS if python_blocks(p)], ids=lambda p: p.stem)
def test_tutorial_runs(path, tmp_path):
    run_blocks(path, tmp_path)
    assert not (ROOT / "options.pt").exists()


def test_readme_examples(tmp_path):
    """The README's quickstart labels the planted options well, and its DQN example stores multi-step decisions."""
    from torchrl_options.testing import label_accuracy

    before = sorted(p.name for p in ROOT.iterdir())
    namespace = run_blocks(ROOT / "README.md", tmp_path)
    assert sorted(p.name for p in ROOT.iterdir()) == before  # nothing written into the repository
    accuracy = label_accuracy(namespace["seg"].options, namespace["data"]["true_option"])
    assert accuracy > 0.9, accuracy  # the README quotes 92.8%
    rb = namespace["rb"]
    assert len(rb) > 0 and (rb[:]["steps_to_next_obs"] > 1).any()  # options ran: some decisions took k > 1 steps
    assert torch.isfinite(namespace["loss_value"])


def test_readme_is_short_and_links_exist():
    readme = (ROOT / "README.md").read_text()
    assert len(readme.encode()) < 15_000
    assert 'pip install -e ".[test]" && python -m pytest' in readme  # the command .ci/run runs
    assert "python -m pytest" in (ROOT / ".ci" / "run").read_text().splitlines()[-1]
    for target in re.findall(r"\]\(((?:docs|results)/[^)#]+)", readme):
        assert (ROOT / target).exists(), f"README links to {target}, which does not exist"


def load_conf():
    """``docs/conf.py`` as a module (it imports nothing from Sphinx at its top)."""
    spec = importlib.util.spec_from_file_location("docs_conf", DOCS / "conf.py")
    conf = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(conf)
    return conf


def test_api_reference_covers_every_subpackage():
    import torchrl_options

    public = {f"torchrl_options.{m.name}" for m in pkgutil.iter_modules(torchrl_options.__path__)
              if not m.name.startswith("_")}
    assert public <= set(load_conf().API_MODULES), public - set(load_conf().API_MODULES)


_MISSING = [m for m in ("sphinx", "myst_parser", "furo") if importlib.util.find_spec(m) is None]


@pytest.mark.skipif(bool(_MISSING), reason=f"the docs extra is not installed (missing {_MISSING}): "
                                           'pip install -e ".[docs]"')
def test_docs_build(tmp_path):
    """``sphinx-build -W --keep-going -b html docs <tmp>``: every page and docstring renders without a warning."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    command = [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html", "-d",
               str(tmp_path / "doctrees"), str(DOCS), str(tmp_path / "html")]
    result = subprocess.run(command, capture_output=True, text=True, cwd=ROOT, env=env, timeout=900)
    assert result.returncode == 0, result.stdout[-5000:] + result.stderr[-10000:]
    html = tmp_path / "html" / "api"
    index = (html / "index.html").read_text()
    import torchrl_options

    for name in torchrl_options.__all__:  # every top-level name is linked to its documentation
        assert re.search(rf'href="[\w.]+\.html#torchrl_options\.[\w.]+\.{name}"', index), name
    for module_name in load_conf().API_MODULES:  # every public name of every subpackage has an entry
        module = importlib.import_module(module_name)
        page = (html / f"{module_name.split('.', 1)[1]}.html").read_text()
        missing = [n for n in getattr(module, "__all__", ()) if f'id="{module_name}.{n}"' not in page]
        assert not missing, f"{module_name}: no API entry for {missing}"
