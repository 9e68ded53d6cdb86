"""libLLVM discovery for Dr.Jit: never LLVM < 16, never a silent fall-back."""
import pytest

import suite.core.llvm as llvm


def test01_version_is_read_from_common_file_names():
    assert llvm.llvm_major("/usr/lib/x86_64-linux-gnu/libLLVM-19.so") == 19
    assert llvm.llvm_major("/usr/lib/libLLVM.so.18.1") == 18
    assert llvm.llvm_major("/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1") == 15


def test02_newest_llvm_of_at_least_16_is_chosen(monkeypatch):
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    monkeypatch.setattr(llvm, "candidates", lambda: [(19, "/x/libLLVM-19.so"), (15, "/x/libLLVM-15.so")])
    assert llvm.find_libllvm() == "/x/libLLVM-19.so"


def test03_only_llvm_15_is_an_error_that_names_the_fix(monkeypatch):
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    monkeypatch.setattr(llvm, "candidates", lambda: [(15, "/x/libLLVM-15.so")])
    with pytest.raises(llvm.LLVMNotFound, match="libllvm19") as info:
        llvm.find_libllvm()
    assert "LLVM 15" in str(info.value)


def test04_explicit_path_is_checked(monkeypatch, tmp_path):
    old = tmp_path / "libLLVM-15.so"
    old.write_bytes(b"")
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(old))
    with pytest.raises(llvm.LLVMNotFound, match="fmaximum"):
        llvm.find_libllvm()
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(tmp_path / "missing.so"))
    with pytest.raises(llvm.LLVMNotFound, match="does not exist"):
        llvm.find_libllvm()


def test05_this_machine_has_a_working_llvm_backend():
    """The set-up installed a libLLVM that renders (the probe runs in a child process)."""
    from suite.core.env import check_llvm_backend

    assert llvm.llvm_major(check_llvm_backend()) >= llvm.MIN_LLVM_MAJOR
