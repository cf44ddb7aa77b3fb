"""jaxdenoise: Monte Carlo denoisers as pure, jit-compiled JAX functions, measured error against time.

Public API::

    import jaxdenoise as jd
    buffers, attrs = jd.read_buffers("frame.exr")
    image = jd.denoise(buffers, method="lbf")        # shipped weights
    infer = jd.load("lbf")                           # jitted inference function
    video = jd.denoise_sequence(frames, method="lbf") # a sequence (recurrent / windowed / per frame)
    jd.method_names()                                # registered method names
    jd.write_image("out.exr", image); jd.write_display("out.png", image, exposure=0)  # linear / sRGB
    jd.runtime.keep_memory()                         # opt-in: the CLI's faster allocator setting (glibc)
"""
from . import runtime
from .api import denoise, denoise_sequence, load
from .buffers import Buffers, BuffersError, stack
from .errors import JaxdenoiseError, JaxdenoiseWarning
from .methods import MethodError
from .methods import names as method_names

# EXR I/O needs OpenImageIO; it is imported on first use so that `jaxdenoise` and its training path
# import on machines without it (a GPU box training from an exported cache).
_IO_NAMES = ("ExrError", "buffers_from_channels", "read_buffers", "read_image", "read_sequence", "write_buffers", "write_image",
             "write_display")


def __getattr__(name: str):
    if name in _IO_NAMES:
        from . import io

        return getattr(io, name)
    raise AttributeError(f"module 'jaxdenoise' has no attribute {name!r}")

# The one version number (pyproject.toml reads it): bumped whenever outputs change (a method's
# result, a file format, a weight), each bump listed in CHANGELOG.md.
__version__ = "0.9.24"

__all__ = [
    "Buffers", "BuffersError", "ExrError", "JaxdenoiseError", "JaxdenoiseWarning", "MethodError", "denoise", "denoise_sequence", "load", "method_names",
    "buffers_from_channels", "read_buffers", "read_image", "read_sequence", "stack", "write_buffers", "write_image", "write_display",
    "runtime", "__version__",
]
