"""Stamps and headers: float seconds (the project's convention) <-> builtin_interfaces/Time, exactly.

``seconds_to_ns`` takes the float's exact binary value (no ``s * 1e9`` rounding, which is off by up to 128 ns at
today's epoch), and ``ns_to_seconds`` is correctly rounded, so float -> Time -> float is the identity. The reverse,
Time -> float -> Time, is exact only down to the float's resolution (about 240 ns for stamps near 2e9 s).
"""
from __future__ import annotations

import math
from fractions import Fraction

from builtin_interfaces.msg import Time
from std_msgs.msg import Header

_NS_PER_S = 1_000_000_000
_MAX_NS = (2**31 - 1) * _NS_PER_S + _NS_PER_S - 1  # builtin_interfaces/Time.sec is int32


def seconds_to_ns(seconds: float) -> int:
    """Float seconds -> the nearest integer nanoseconds of the float's exact value."""
    if not math.isfinite(seconds) or seconds < 0:
        raise ValueError(f"stamp {seconds!r} s is not a finite non-negative number of seconds")
    ns = round(Fraction(seconds) * _NS_PER_S)
    if ns > _MAX_NS:
        raise ValueError(f"stamp {seconds!r} s does not fit builtin_interfaces/Time (int32 seconds)")
    return ns


def ns_to_seconds(ns: int) -> float:
    """Integer nanoseconds -> float seconds (correctly rounded)."""
    return ns / _NS_PER_S


def ns_to_time(ns: int) -> Time:
    if not 0 <= ns <= _MAX_NS:
        raise ValueError(f"stamp {ns} ns does not fit builtin_interfaces/Time")
    return Time(sec=ns // _NS_PER_S, nanosec=ns % _NS_PER_S)


def time_to_ns(stamp: Time) -> int:
    return stamp.sec * _NS_PER_S + stamp.nanosec


def seconds_to_time(seconds: float) -> Time:
    return ns_to_time(seconds_to_ns(seconds))


def time_to_seconds(stamp: Time) -> float:
    return ns_to_seconds(time_to_ns(stamp))


def make_header(stamp: float, frame_id: str) -> Header:
    """A std_msgs/Header at ``stamp`` float seconds in ``frame_id``."""
    return Header(stamp=seconds_to_time(stamp), frame_id=frame_id)


def header_seconds(header: Header) -> float:
    return time_to_seconds(header.stamp)
