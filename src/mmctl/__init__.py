"""mmctl: control daemon of a mobile manipulator for physical human-robot interaction."""

__version__ = "0.1.0"
