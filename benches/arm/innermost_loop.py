"""Prints, as llvm-mca input, the innermost loop of one function of an aarch64 disassembly
(`aarch64-linux-gnu-objdump -d --no-show-raw-insn`) that holds the most of one mnemonic:
a loop is the instructions from a backward branch's target to the branch, innermost when
no loop of another target lies inside it.

python3 innermost_loop.py DISASSEMBLY FUNCTION_SUBSTRING MNEMONIC
"""

import re
import sys


def function_body(lines, name):
    body, inside = [], False
    for line in lines:
        if re.match(r"^[0-9a-f]+ <.*>:$", line):
            if inside:
                break
            inside = name in line
            continue
        match = re.match(r"^\s*([0-9a-f]+):\s*(.*)$", line) if inside else None
        if match:
            body.append((int(match.group(1), 16), match.group(2).split("//")[0].strip()))
    return body


def main():
    path, name, mnemonic = sys.argv[1:4]
    body = function_body(open(path).read().split("\n"), name)
    loops = []
    for address, instruction in body:
        branch = re.match(r"^(b\.\w+|b|cbnz|cbz|tbnz|tbz)\s+(?:.*,\s*)?([0-9a-f]+) <", instruction)
        if branch and int(branch.group(2), 16) < address:
            loops.append((int(branch.group(2), 16), address))
    best = None
    for target, address in loops:
        # Innermost only (a loop of another header inside it makes it an outer one): an
        # outer loop holds its inner loops' multiplies too, more than any one of them when
        # the compiler made copies of a tile's loop.
        if any(target < inner[0] and inner[1] <= address for inner in loops):
            continue
        loop = [text for at, text in body if target <= at <= address]
        count = sum(1 for text in loop if text.split()[0] == mnemonic)
        # The most of the mnemonic, then the shortest loop.
        if count and (best is None or (count, -len(loop)) > best[0]):
            best = ((count, -len(loop)), loop)
    if best is None:
        sys.exit(f"no loop with {mnemonic} in {name}")
    print("loop:")
    for text in best[1]:
        print(re.sub(r"([0-9a-f]+) <[^>]*>$", "loop", text))


if __name__ == "__main__":
    main()
