"""togglecf: a data-driven toggling-gain complementary filter for IMU orientation, on BROAD.

Conventions (see ``togglecf.quaternion``): quaternions ``[w, x, y, z]``, Hamilton product,
sensor -> earth, earth frame ENU; SI units (rad/s, m/s², µT); time series ``(N, 3)``/``(N, 4)``
float64, one sample a row; the sampling rate is always passed explicitly.
"""
__version__ = "0.1.0"
