"""The README's Python examples run as written."""

import pathlib
import re

README = pathlib.Path(__file__).resolve().parent.parent / "README.md"


def test_readme_examples_run(capsys):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert len(blocks) >= 2
    namespace: dict = {}
    for block in blocks:
        exec(compile(block, str(README), "exec"), namespace)  # noqa: S102
    out = capsys.readouterr().out
    assert out.count("\n") >= 3
    # The quick example's first line: simulated and closed-form final rates agree.
    traj, jnp = namespace["traj"], namespace["jnp"]
    assert float(jnp.abs(traj.t_final - namespace["rod"].fall_time(0.05))) < 1e-6


def test_readme_commands_match_ci():
    text = README.read_text()
    ci = (README.parent / ".ci" / "run").read_text()
    test_command = 'python -m pip install -e ".[test]" && python -m pytest'
    assert test_command in text and test_command in ci
    assert "python -m pip install . && jaxdyn run" in text
