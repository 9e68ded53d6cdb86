"""Prints the path of a libLLVM that Dr.Jit's LLVM backend can use, or explains the fix (exit 2).

Kept free of project imports so that the set-up can call it before anything is installed.
"""
import sys
import os

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from suite.core.llvm import find_libllvm, LLVMNotFound  # noqa: E402

try:
    print(find_libllvm())
except LLVMNotFound as exc:
    print(f"setup: {exc}", file=sys.stderr)
    sys.exit(2)
