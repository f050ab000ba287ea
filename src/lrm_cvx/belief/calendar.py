"""A record's own calendar: its cadence, its stamps and the period each stamp stands for.

:class:`RecordCalendar` reads a record's time coordinate (``datetime64``, cftime dates or plain
numbers) and answers the field loop's time questions the way the record itself would
(docs/monitoring.md). Dates outside ``datetime64[ns]``'s range are refused in one line.
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from .._validation import NS_RANGE, datetime_ns
from ..errors import DataError
from ..glrm.dynamics import time_numbers

__all__ = ["RecordCalendar"]

_DAY_US = 86_400_000_000
_MEAN_MONTH_DAYS = 365.2425 / 12


def _fields(times: np.ndarray) -> dict[str, np.ndarray]:
    """Year, month, day, microseconds into the day, day of year and days in the month (int64
    arrays) of ``datetime64`` or cftime ``times``."""
    import xarray as xr

    if np.issubdtype(times.dtype, np.datetime64):
        idx: Any = pd.DatetimeIndex(times)
    else:
        idx = xr.CFTimeIndex(times)
    us = ((np.asarray(idx.hour, np.int64) * 60 + np.asarray(idx.minute, np.int64)) * 60
          + np.asarray(idx.second, np.int64)) * 1_000_000 + np.asarray(idx.microsecond,
                                                                        np.int64)
    return {"year": np.asarray(idx.year, np.int64), "month": np.asarray(idx.month, np.int64),
            "day": np.asarray(idx.day, np.int64), "us": us,
            "doy": np.asarray(idx.day_of_year if hasattr(idx, "day_of_year")
                              else idx.dayofyear, np.int64),
            "dim": np.asarray(idx.days_in_month, np.int64)}


def _one(t: Any) -> tuple[int, int, int, int, int]:
    """``(year, month, day, us into the day, day of year)`` of one date (``_fields``' for
    one time, without building an index)."""
    if hasattr(t, "calendar"):
        c, doy = t, int(t.dayofyr)
    else:
        c = pd.Timestamp(t)
        doy = int(c.day_of_year)
    us = ((c.hour * 60 + c.minute) * 60 + c.second) * 1_000_000 + c.microsecond
    return int(c.year), int(c.month), int(c.day), int(us), doy


@dataclass
class RecordCalendar:
    """The cadence and stamp convention of a record (module docstring); build with :meth:`of`.

    ``kind`` is ``"months"`` (``n`` months a step), ``"grid"`` (a fixed ``step``: days for
    dates, coordinate units for numbers, anchored at the record's last time), ``"dayofyear"``
    (``step`` whole days restarting each year at day ``offset + 1``) or ``"irregular"`` (no
    convention found: one ``step`` on from any time, as the dynamics count steps).
    """

    kind: str
    time_kind: str                      # "datetime" | "cftime" | "numeric"
    calendar: str | None
    step: float                         # days (or coordinate units)
    n: int = 0                          # months a step ("months")
    phase: int = 0                      # the record's month index modulo n ("months")
    anchor: Any = None                  # the record's last time ("grid")
    offset: int = 0                     # first day of the year - 1 ("dayofyear")
    day_us: int = 0                     # the stamps' time into the day ("dayofyear")
    day_of_month: tuple[int, int] | None = None   # (day, us into the day) of every stamp
    from_end: tuple[int, int] | None = None       # (days before the month's end, us)
    fraction: float | None = None       # the stamps' fraction of their month
    month_stamps: dict[int, tuple[int, int]] = field(default_factory=dict)

    # ------------------------------------------------------------------ construction
    @classmethod
    def of(cls, times: Any, step: float | None = None) -> RecordCalendar:
        """The calendar of the record whose time coordinate is ``times`` (sorted, >= 1 time).
        ``step``: the dynamics' step (default: the median spacing of ``times``)."""
        values = np.asarray(getattr(times, "values", times)).ravel()
        t, kind, calendar = time_numbers(values, "time")
        d = np.diff(t)
        if step is None:
            step = float(np.median(d)) if d.size and np.all(d > 0) else 1.0
        step = float(step)
        base = {"time_kind": kind, "calendar": calendar, "step": step}
        if values.size == 0:
            return cls("irregular", **base)
        if kind != "numeric":
            months = cls._months(values, step, base)
            if months is not None:
                return months
        tol = 1e-6 if kind != "numeric" else 1e-9 * max(abs(step), 1.0)
        k = (t - t[-1]) / step
        if np.all(np.abs(k - np.round(k)) * step <= tol):
            return cls("grid", anchor=values[-1], **base)
        if kind != "numeric" and abs(step - round(step)) < 1e-9 and step >= 1:
            f = _fields(values)
            s = int(round(step))
            r = (f["doy"] - 1) % s
            if np.all(r == r[0]) and np.all(f["us"] == f["us"][0]):
                return cls("dayofyear", offset=int(r[0]), day_us=int(f["us"][0]), **base)
        return cls("irregular", **base)

    @classmethod
    def _months(cls, values: np.ndarray, step: float, base: dict) -> RecordCalendar | None:
        """The month-cadence calendar of a record stepping by whole calendar months, or None."""
        n = int(round(step / _MEAN_MONTH_DAYS))
        if n < 1 or not 27 * n <= step <= 32 * n:
            return None
        f = _fields(values)
        index = f["year"] * 12 + f["month"] - 1
        dm = np.diff(index)
        if np.any(dm <= 0) or np.any(dm % n):
            return None
        offset = (f["day"] - 1) * _DAY_US + f["us"]
        day_of_month = None
        if np.all(f["day"] == f["day"][0]) and np.all(f["us"] == f["us"][0]):
            day_of_month = (int(f["day"][0]), int(f["us"][0]))
        before_end = f["dim"] - f["day"]
        from_end = None
        if np.all(before_end == before_end[0]) and np.all(f["us"] == f["us"][0]):
            from_end = (int(before_end[0]), int(f["us"][0]))
        frac = offset / (f["dim"] * float(_DAY_US))
        fraction = float(np.median(frac)) if np.ptp(frac) * 31 * 1440 <= 1.0 else None  # 1 min
        stamps: dict[int, set] = {}
        for m, day, us in zip(f["month"].tolist(), f["day"].tolist(), f["us"].tolist(),
                              strict=True):  # twelve months at most: a small table
            stamps.setdefault(m, set()).add((day, us))
        table = {m: next(iter(s)) for m, s in stamps.items() if len(s) == 1}
        return cls("months", n=n, phase=int(index[0] % n), day_of_month=day_of_month,
                   from_end=from_end, fraction=fraction, month_stamps=table, **base)

    # ------------------------------------------------------------------ the questions
    def describe(self) -> str:
        """The cadence in words (for messages)."""
        if self.kind == "months":
            return {1: "monthly", 12: "yearly"}.get(self.n, f"every {self.n} months")
        unit = "" if self.time_kind == "numeric" else " day(s)"
        return f"every {self.step:g}{unit}"

    def stamp_of(self, t: Any) -> Any:
        """The record's stamp whose period holds ``t`` (``t`` itself when it is a stamp)."""
        if self.kind == "months":
            return self._month_stamp(self._month_index(t), t)
        if self.kind == "grid":
            k = self._grid_index(t)
            return t if self._on_grid(t, k) else self._grid_time(k)
        if self.kind == "dayofyear":
            return self._doy_time(*self._doy_index(t))
        return t

    def next_stamp(self, t: Any) -> Any:
        """The record's stamp one step after the period holding ``t``: the next plan's time."""
        if self.kind == "months":
            return self._month_stamp(self._month_index(t) + self.n, t)
        if self.kind == "dayofyear":
            year, j = self._doy_index(t)
            if self.offset + 1 + (j + 1) * int(round(self.step)) > self._days_in_year(year):
                return self._doy_time(year + 1, 0)
            return self._doy_time(year, j + 1)
        return self._add(self.stamp_of(t), self.step)

    def same_period(self, a: Any, b: Any) -> bool:
        """Whether ``a`` and ``b`` lie in the period of one stamp (the same snapshot)."""
        if self.kind == "months":
            return self._month_index(a) == self._month_index(b)
        if self.kind == "grid":
            return self._grid_index(a) == self._grid_index(b)
        if self.kind == "dayofyear":
            return self._doy_index(a) == self._doy_index(b)
        return abs(self._days(a, b)) < 0.5 * self.step

    # ------------------------------------------------------------------ months
    def _month_index(self, t: Any) -> int:
        year, month = _one(t)[:2]
        m = year * 12 + month - 1
        n, p = self.n, self.phase
        if n % 12 == 0:  # whole years: the block of n // 12 calendar years holding t
            base = p - p % 12
            return base + n * ((m - base) // n) + p % 12
        return p + n * ((m - p + (n - 1) // 2) // n)  # the n months around the stamp

    def _month_stamp(self, index: int, t: Any) -> Any:
        """The stamp of month ``index`` (``year * 12 + month - 1``) by the record's convention;
        ``t``'s day and time in that month when the record has none."""
        import cftime

        year, month0 = divmod(index, 12)
        cal = self.calendar or "proleptic_gregorian"
        first = cftime.datetime(year, month0 + 1, 1, calendar=cal)
        dim = int(first.daysinmonth)
        if self.day_of_month is not None:
            day, us = self.day_of_month
            offset = (min(day, dim) - 1) * _DAY_US + us
        elif self.from_end is not None:
            days, us = self.from_end
            offset = max(dim - 1 - days, 0) * _DAY_US + us
        elif self.fraction is not None:
            offset = int(round(self.fraction * dim * 86_400)) * 1_000_000
        elif month0 + 1 in self.month_stamps:
            day, us = self.month_stamps[month0 + 1]
            offset = (min(day, dim) - 1) * _DAY_US + us
        else:
            _, _, day, us, _ = _one(t)
            offset = (min(day, dim) - 1) * _DAY_US + us
        return self._native(first + _dt.timedelta(microseconds=offset))

    # ------------------------------------------------------------------ fixed steps
    def _days(self, a: Any, b: Any) -> float:
        """``b - a`` in days (or coordinate units)."""
        if self.time_kind == "numeric":
            return float(b) - float(a)
        arr = np.empty(2, dtype=object)
        arr[:] = [a, b]
        if self.time_kind == "datetime":
            arr = arr.astype("datetime64[ns]")
        return float(time_numbers(arr, "time")[0][1])

    def _whole_days(self) -> bool:
        return self.time_kind != "numeric" and self.step >= 1 and abs(
            self.step - round(self.step)) < 1e-9

    def _grid_index(self, t: Any) -> int:
        if self._whole_days():  # a stamp stands for the calendar days up to the next one
            day = self._days(self._midnight(self.anchor), self._midnight(t))
            return int(np.floor(round(day) / round(self.step)))
        return int(np.round(self._days(self.anchor, t) / self.step))

    def _on_grid(self, t: Any, k: int) -> bool:
        tol = 1e-6 if self.time_kind != "numeric" else 1e-9 * max(abs(self.step), 1.0)
        return abs(self._days(self.anchor, t) - k * self.step) <= tol

    def _grid_time(self, k: int) -> Any:
        return self._add(self.anchor, k * self.step) if k else self.anchor

    def _midnight(self, t: Any) -> Any:
        if self.time_kind == "datetime":
            return np.datetime64(t, "D").astype("datetime64[ns]")
        return t.replace(hour=0, minute=0, second=0, microsecond=0)

    def _add(self, t: Any, days: float) -> Any:
        """``t`` plus ``days`` (coordinate units for numbers)."""
        if self.time_kind == "numeric":
            return float(t) + days
        if self.time_kind == "datetime":
            try:
                later = pd.Timestamp(t) + pd.Timedelta(days=days)
            except (OverflowError, ValueError):
                later = None
            if later is None or later > pd.Timestamp.max:
                raise DataError(f"the time {days:g} day(s) after {t} is past {NS_RANGE[1]}, the "
                                "last date a datetime64[ns] time coordinate can hold")
            return later.as_unit("ns").to_datetime64()
        return t + _dt.timedelta(days=days)

    # ------------------------------------------------------------------ day of year
    def _days_in_year(self, year: int) -> int:
        import cftime

        cal = self.calendar or "proleptic_gregorian"
        return int((cftime.datetime(year + 1, 1, 1, calendar=cal)
                    - cftime.datetime(year, 1, 1, calendar=cal)).days)

    def _doy_index(self, t: Any) -> tuple[int, int]:
        """``(year, j)``: ``t`` lies in the period of that year's ``j``-th stamp."""
        year, _, _, _, doy = _one(t)
        pos = doy - 1 - self.offset
        s = int(round(self.step))
        if pos < 0:  # before the year's first stamp: the previous year's last period
            year -= 1
            pos = self._days_in_year(year) - 1 - self.offset
        return year, pos // s

    def _doy_time(self, year: int, j: int) -> Any:
        import cftime

        cal = self.calendar or "proleptic_gregorian"
        days = self.offset + j * int(round(self.step))
        c = cftime.datetime(year, 1, 1, calendar=cal) + _dt.timedelta(
            days=days, microseconds=self.day_us)
        return self._native(c)

    # ------------------------------------------------------------------ types
    def _native(self, c: Any) -> Any:
        """The cftime date ``c`` in the record's own time type."""
        if self.time_kind == "cftime":
            return c
        text = f"{c.year:04d}-{c.month:02d}-{c.day:02d}T{c.hour:02d}:{c.minute:02d}:" \
               f"{c.second:02d}.{c.microsecond:06d}"
        return datetime_ns(text, "the next time")
