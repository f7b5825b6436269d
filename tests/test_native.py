"""The one loader of the compiled kernels (usdml/native.py): what a wrapper declares is what it gets."""

import ctypes

import pytest

from usdml.lighting.lgh import native as lgh_native
from usdml.native import Extension, kernel_label, path_line
from usdml.visibility.insm import native as insm_native
from usdml.visibility.svo import native as svo_native
from usdml.visibility.voxel import native as voxel_native

WRAPPERS = [voxel_native, svo_native, insm_native, lgh_native]


def test_a_missing_extension_is_none_and_says_why():
    ext = Extension("_no_such_kernel", {"f": (ctypes.c_int, [ctypes.c_int])})
    lib, why = ext.load()
    assert lib is None and ext.library() is None and why.startswith("not built")
    assert path_line("compiled kernel", why, 0, "queries").startswith("Warp kernels (the compiled kernel is not built")


@pytest.mark.parametrize("wrapper", WRAPPERS, ids=lambda m: m.__name__.rsplit(".", 1)[-1])
def test_every_wrapper_declares_its_functions_once(wrapper):
    """Each wrapper's functions carry the declared signatures, and the library is opened once."""
    lib = wrapper.library()
    if lib is None:
        pytest.skip(wrapper.describe())
    assert wrapper.EXTENSION.library() is lib
    for name, (restype, argtypes) in wrapper.EXTENSION.functions.items():
        fn = getattr(lib, name)
        assert fn.restype == restype and list(fn.argtypes) == list(argtypes), name
    assert wrapper.describe()


def test_kernel_labels_follow_the_register_width():
    assert [kernel_label(w) for w in (16, 8, 1)] == ["native-avx512", "native-avx2", "native-scalar"]


def test_a_library_left_by_the_flat_layout_is_named(tmp_path, monkeypatch):
    """An editable install made before the kernels had a folder per method left ``kernels/_voxelq*.so`` where
    nothing looks now; the reason the compiled path is off names it (and a reinstall builds it in its folder)."""
    import usdml.kernels
    from usdml.native import open_extension

    (tmp_path / "_nosuch.cpython-311-x86_64-linux-gnu.so").write_bytes(b"")
    monkeypatch.setattr(usdml.kernels, "__path__", [*usdml.kernels.__path__, str(tmp_path)])
    lib, why = open_extension("voxel._nosuch")
    assert lib is None and why.startswith("not built (") and \
        why.endswith("; _nosuch.cpython-311-x86_64-linux-gnu.so was built for the layout before kernels/voxel/)")
    assert "was built for" not in open_extension("voxel._other")[1]
