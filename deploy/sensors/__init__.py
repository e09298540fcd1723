"""Real-sensor adapters for a vehicle computer: GNSS (NMEA, UBX) and IMU text to bus messages.

The parsers here are pure (bytes or lines in, :mod:`transport.messages` out, errors counted);
:mod:`deploy.sensors.driver` is the I/O shell (serial ports, files, pacing, publishing).
"""
