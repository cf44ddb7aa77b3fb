"""jaxdenoise: Monte Carlo denoisers as pure, jit-compiled JAX functions, measured error against time.

Public API::

    import jaxdenoise as jd
    buffers, attrs = jd.read_buffers("frame.exr")
    image = jd.denoise(buffers, method="lbf")        # shipped weights
    infer = jd.load("lbf")                           # jitted inference function
    video = jd.denoise_sequence(frames, method="lbf") # a sequence (recurrent / windowed / per frame)
    jd.method_names()                                # registered method names
"""
from .api import denoise, denoise_sequence, load
from .buffers import Buffers, BuffersError, stack
from .io import ExrError, read_buffers, read_image, read_sequence, write_buffers, write_image
from .methods import MethodError
from .methods import names as method_names

__version__ = "0.1.0"

__all__ = [
    "Buffers", "BuffersError", "ExrError", "MethodError", "denoise", "denoise_sequence", "load", "method_names",
    "read_buffers", "read_image", "read_sequence", "stack", "write_buffers", "write_image",
    "__version__",
]
