"""Live orientation: IMU lines from a serial port, a file or stdin through any filter."""
from togglecf.live.stream import StreamConfig, StreamProcessor

__all__ = ["StreamConfig", "StreamProcessor"]
