"""The suite's guard against children that exit at start-up without a word (``run_child`` in
conftest.py): such a child is started again, any other outcome is returned as it is."""

from __future__ import annotations

import sys

import pytest
from conftest import run_child

# exits 1 without a word the first ``fails`` times it is started (a count in a file), then
# prints "ran" and exits with ``rc``
CHILD = """
import sys
from pathlib import Path
count, fails, rc, say = Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
n = int(count.read_text()) if count.exists() else 0
count.write_text(str(n + 1))
if n < fails:
    if say == "mpirun":  # the report mpirun writes when a rank exits so
        sys.stderr.write("-" * 55 + "\\nPrimary job  terminated normally, but 1 process returned\\n"
                         "a non-zero exit code. Per user-direction, the job has been aborted.\\n"
                         + "-" * 55 + "\\n" + "-" * 74 + "\\nmpirun detected that one or more "
                         "processes exited with non-zero status, thus causing\\nthe job to be "
                         "terminated. The first process to do so was:\\n\\n  Process name: "
                         "[[1234,1],1]\\n  Exit code:    1\\n" + "-" * 74 + "\\n")
    elif say:
        print(say)
    sys.exit(1)
print("ran")
sys.exit(rc)
"""


def _child(tmp_path, fails: int, rc: int = 0, say: str = ""):
    script = tmp_path / "child.py"
    script.write_text(CHILD)
    return [sys.executable, str(script), str(tmp_path / "count"), str(fails), str(rc), say]


def _starts(tmp_path) -> int:
    return int((tmp_path / "count").read_text())


@pytest.mark.parametrize("say", ["", "mpirun"])
def test_silent_start_exits_are_started_again(tmp_path, say):
    with pytest.warns(UserWarning, match="without a word") as seen:
        r = run_child(_child(tmp_path, fails=2, say=say))
    assert r.returncode == 0 and r.stdout == "ran\n"
    assert _starts(tmp_path) == 3 and len(seen) == 2


def test_a_child_that_keeps_exiting_silently_fails(tmp_path):
    with pytest.warns(UserWarning):
        r = run_child(_child(tmp_path, fails=5), retries=2)
    assert r.returncode == 1 and _starts(tmp_path) == 3


@pytest.mark.parametrize("fails,rc,say", [(1, 0, "an error of ours"), (0, 1, ""), (0, 2, "")])
def test_other_exits_are_returned_as_they_are(tmp_path, recwarn, fails, rc, say):
    """A child that says a word, or exits 1 after its work, or with another code, is not
    started again."""
    r = run_child(_child(tmp_path, fails=fails, rc=rc, say=say))
    assert r.returncode == (1 if fails else rc) and _starts(tmp_path) == 1
    assert not [w for w in recwarn if "without a word" in str(w.message)]


def test_check_raises_after_the_retries(tmp_path):
    with pytest.warns(UserWarning), pytest.raises(Exception) as err:
        run_child(_child(tmp_path, fails=5), retries=1, check=True)
    assert "returned non-zero exit status 1" in str(err.value) and _starts(tmp_path) == 2
