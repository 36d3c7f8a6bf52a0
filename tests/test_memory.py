"""flgd.memory: the heap's free pages go back to the system when the daemon trims after a cycle."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from tests.fakes.daemon import REPO

# Run apart: the test process's own heap must not blur the numbers.
_PROGRAM = textwrap.dedent("""
    import ctypes, sys
    from flgd.memory import trim_heap
    def rss():
        for line in open("/proc/self/status"):
            if line.startswith("VmRSS"):
                return int(line.split()[1]) * 1024
    blocks = [ctypes.create_string_buffer(100 * 1024) for _ in range(2000)]  # 200 MB of heap blocks
    pin = ctypes.create_string_buffer(100 * 1024)  # above them: the heap's top cannot shrink by itself
    del blocks
    before = rss()
    trimmed = trim_heap() if sys.argv[1] == "trim" else False
    print(before, rss(), trimmed)
""")


def _run(mode: str) -> tuple[int, int, str]:
    out = subprocess.run([sys.executable, "-c", _PROGRAM, mode], capture_output=True, text=True, cwd=REPO,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    before, after, trimmed = out.stdout.split()
    return int(before), int(after), trimmed


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc_trim")
def test_freed_heap_memory_is_returned_after_a_trim_and_kept_without_one():
    before, after, trimmed = _run("keep")
    assert after > before - 20 * 2**20, "without a trim the freed blocks stay resident"
    before, after, trimmed = _run("trim")
    assert trimmed == "True" and after < before - 150 * 2**20, (before, after)
