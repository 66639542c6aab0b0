import os
import subprocess
import sys

import pytest

from ngp_mi import backend
from ngp_mi.backend import BackendError, find_libllvm, llvm_version


@pytest.mark.parametrize("name, version", [
    ("libLLVM-19.so", 19), ("libLLVM-14.0.6.so.1", 14), ("libLLVM.so.19.1", 19),
    ("libLLVM.18.dylib", 18), ("libLLVM.so", None),
])
def test_llvm_version_from_file_name(tmp_path, name, version):
    path = tmp_path / name
    path.write_bytes(b"")
    assert llvm_version(path) == version


def test_llvm_version_from_folder_and_link_target(tmp_path):
    folder = tmp_path / "llvm-17" / "lib"
    folder.mkdir(parents=True)
    (folder / "libLLVM.so").write_bytes(b"")
    assert llvm_version(folder / "libLLVM.so") == 17
    (tmp_path / "libLLVM.so.18.1").write_bytes(b"")
    os.symlink(tmp_path / "libLLVM.so.18.1", tmp_path / "libLLVM.so")
    assert llvm_version(tmp_path / "libLLVM.so") == 18


def _touch(folder, *names):
    for name in names:
        (folder / name).write_bytes(b"x")


def test_find_libllvm_picks_newest_usable(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir(), b.mkdir()
    _touch(a, "libLLVM-15.so", "libLLVM-17.so.1", "libLLVMSupport.a")
    _touch(b, "libLLVM.so.19.1")
    os.symlink(b / "libLLVM.so.19.1", b / "libLLVM-19.so")
    found = find_libllvm([str(a), str(b), str(tmp_path / "missing")], env={})
    assert llvm_version(found) == 19


def test_find_libllvm_rejects_llvm15_with_install_hint(tmp_path):
    _touch(tmp_path, "libLLVM-15.so", "libLLVM-14.so.1")
    with pytest.raises(BackendError) as info:
        find_libllvm([str(tmp_path)], env={})
    message = str(info.value)
    assert "libLLVM-15.so (LLVM 15)" in message and "apt-get install libllvm19" in message


def test_find_libllvm_honours_environment(tmp_path):
    _touch(tmp_path, "libLLVM-19.so", "libLLVM-15.so", "custom-llvm.so")
    env_path = str(tmp_path / "custom-llvm.so")
    assert str(find_libllvm([str(tmp_path)], env={"DRJIT_LIBLLVM_PATH": env_path})) == env_path
    with pytest.raises(BackendError, match="does not exist"):
        find_libllvm([], env={"DRJIT_LIBLLVM_PATH": str(tmp_path / "nope.so")})
    with pytest.raises(BackendError, match="is LLVM 15"):
        find_libllvm([], env={"DRJIT_LIBLLVM_PATH": str(tmp_path / "libLLVM-15.so")})


def test_loaded_backend_is_usable(mi):
    b = backend.load()
    assert b.variant in backend.AUTO_VARIANTS or os.environ.get(backend.ENV_VARIANT)
    assert mi.variant() == b.variant
    assert b.threads >= 1
    if b.variant.startswith("llvm"):
        assert llvm_version(b.libllvm) >= backend.MIN_LLVM_VERSION
        assert os.environ["DRJIT_LIBLLVM_PATH"] == str(b.libllvm)
    x = mi.Float([1.0, 2.0]) * 3.0
    assert list(x) == [3.0, 6.0]


def _run_load(**env_overrides):
    env = {**os.environ, **env_overrides}
    code = "from ngp_mi import backend; b = backend.load(); print(b.variant, b.threads)"
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)


def test_variant_and_threads_overrides():
    done = _run_load(NGP_MI_VARIANT="scalar_rgb", NGP_MI_THREADS="1")
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["scalar_rgb", "1"]


def test_unknown_variant_is_a_clear_error():
    done = _run_load(NGP_MI_VARIANT="bogus_variant")
    assert done.returncode != 0
    assert "NGP_MI_VARIANT='bogus_variant' is not a Mitsuba variant" in done.stderr
