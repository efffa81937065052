"""Print the shell commands of README.md's "Quick start" block, one per line.

Comment lines and blank lines are skipped; used by .ci/run so that CI runs exactly the
commands a newcomer copies from the README.
"""

import sys
from pathlib import Path

text = Path(sys.argv[1]).read_text(encoding="utf-8")
section = text.split("## Quick start", 1)[1]
block = section.split("```bash", 1)[1].split("```", 1)[0]
for line in block.splitlines():
    line = line.strip()
    if line and not line.startswith("#"):
        print(line)
