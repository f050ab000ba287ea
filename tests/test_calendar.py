"""A record's own calendar (``lrm_cvx.calendar``): the next stamp, a stamp's period and the
``datetime64[ns]`` range, over the cftime calendars and the common record conventions."""

from __future__ import annotations

import cftime
import numpy as np
import pandas as pd
import pytest
import xarray as xr
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from lrm_cvx._validation import datetime_ns
from lrm_cvx.belief.calendar import RecordCalendar
from lrm_cvx.errors import DataError

CALENDARS = ["standard", "proleptic_gregorian", "noleap", "all_leap", "360_day", "julian"]


def _ns(text: str) -> np.datetime64:
    return np.datetime64(text, "ns")


def _monthly_15th(n: int = 24) -> np.ndarray:
    return (pd.date_range("2008-01-01", periods=n, freq="MS") + pd.Timedelta(days=14)).values


def _cf_mid_month(start: str, n: int, calendar: str = "standard") -> np.ndarray:
    """CF monthly means: each stamp half way through its month (16 Jan 12:00, 15 Feb 00:00,
    15 Feb 12:00 in a leap year, ...)."""
    edges = xr.date_range(start, periods=n + 1, freq="MS", calendar=calendar,
                          use_cftime=calendar != "standard")
    mids = [a + (b - a) / 2 for a, b in zip(edges[:-1], edges[1:], strict=True)]
    return np.asarray(mids, dtype="datetime64[ns]" if calendar == "standard" else object)


# ----------------------------------------------------------------------------- examples
def test_monthly_on_the_15th_goes_to_the_15th_of_the_next_month():
    cal = RecordCalendar.of(_monthly_15th())
    assert cal.kind == "months" and cal.n == 1 and cal.describe() == "monthly"
    # a state off the record's stamps (16 Jan 12:00) plans for the record's 15 Feb
    assert cal.next_stamp(_ns("2010-01-16T12:00")) == _ns("2010-02-15")
    assert cal.next_stamp(_ns("2010-01-15")) == _ns("2010-02-15")
    assert cal.next_stamp(_ns("2010-12-15")) == _ns("2011-01-15")
    # the period of a monthly stamp is its calendar month
    assert cal.same_period(_ns("2010-02-01"), _ns("2010-02-16T12:00"))
    assert cal.same_period(_ns("2010-02-28T23:00"), _ns("2010-02-15"))
    assert not cal.same_period(_ns("2010-03-01"), _ns("2010-02-15"))
    assert cal.stamp_of(_ns("2010-02-27")) == _ns("2010-02-15")


def test_cf_mid_month_stamps_keep_their_fraction_of_the_month():
    times = _cf_mid_month("2005-01-01", 60)
    cal = RecordCalendar.of(times[:30])
    assert cal.fraction == pytest.approx(0.5) and cal.day_of_month is None
    # every month after the record, leap Februaries included (2008: 15 Feb 12:00)
    nxt = [cal.next_stamp(t) for t in times[29:-1]]
    np.testing.assert_array_equal(np.asarray(nxt, "datetime64[ns]"), times[30:])
    assert pd.Timestamp(cal.next_stamp(_ns("2008-01-16T12:00"))) == pd.Timestamp(
        "2008-02-15T12:00")
    assert pd.Timestamp(cal.next_stamp(_ns("2009-01-16T12:00"))) == pd.Timestamp("2009-02-15")


def test_daily_goes_to_the_next_day():
    days = pd.date_range("2013-01-01T12:00", periods=40, freq="D").values
    cal = RecordCalendar.of(days)
    assert cal.kind == "grid"
    assert cal.next_stamp(days[-1]) == _ns("2013-02-10T12:00")
    # a time within a day belongs to that day's stamp; the next stamp is the next day's
    assert cal.stamp_of(_ns("2013-02-11T03:00")) == _ns("2013-02-11T12:00")
    assert cal.next_stamp(_ns("2013-02-11T03:00")) == _ns("2013-02-12T12:00")
    assert cal.same_period(_ns("2013-02-11T00:00"), _ns("2013-02-11T23:59"))
    assert not cal.same_period(_ns("2013-02-11T23:59"), _ns("2013-02-12T00:00"))


def test_yearly_on_a_360_day_calendar_goes_to_the_next_year():
    times = np.array([cftime.datetime(2090 + i, 7, 1, calendar="360_day") for i in range(12)])
    cal = RecordCalendar.of(times)
    assert cal.kind == "months" and cal.n == 12 and cal.describe() == "yearly"
    assert cal.next_stamp(times[-1]) == cftime.datetime(2102, 7, 1, calendar="360_day")
    # a year's stamp stands for that calendar year (30 Feb exists in this calendar)
    feb30 = cftime.datetime(2103, 2, 30, calendar="360_day")
    assert cal.stamp_of(feb30) == cftime.datetime(2103, 7, 1, calendar="360_day")
    assert cal.next_stamp(feb30) == cftime.datetime(2104, 7, 1, calendar="360_day")


def test_noleap_monthly_on_the_first():
    times = np.asarray(xr.date_range("2001-01-01", periods=40, freq="MS", calendar="noleap",
                                     use_cftime=True))
    cal = RecordCalendar.of(times[:36])
    assert [cal.next_stamp(t) for t in times[35:-1]] == list(times[36:])
    assert cal.next_stamp(cftime.datetime(2004, 2, 28, 18, calendar="noleap")) == times[38]


def test_monthly_on_the_31st_keeps_each_month_end():
    ends = (pd.date_range("2009-01-01", periods=24, freq="MS") - pd.Timedelta(days=1)).values
    cal = RecordCalendar.of(ends)  # 31 Dec, 31 Jan, 28 Feb, 31 Mar, ...: each month's last day
    assert cal.day_of_month is None
    assert cal.next_stamp(ends[-1]) == _ns("2010-12-31")
    assert cal.next_stamp(_ns("2011-01-31")) == _ns("2011-02-28")
    short = RecordCalendar.of(ends[:5])  # Dec to Apr: no February's stamp of its own
    assert short.next_stamp(_ns("2012-01-31")) == _ns("2012-02-29")


def test_eight_day_composites_restart_every_year():
    days = np.array([pd.Timestamp(y, 1, 1) + pd.Timedelta(days=8 * j)
                     for y in (2010, 2011, 2012) for j in range(46)], dtype="datetime64[ns]")
    cal = RecordCalendar.of(days)
    assert cal.kind == "dayofyear" and cal.offset == 0
    assert [cal.next_stamp(a) for a in days[:-1]] == list(days[1:])
    assert cal.next_stamp(days[-1]) == _ns("2013-01-01")  # after day 361 (27 Dec): 1 Jan
    assert cal.same_period(_ns("2012-12-31"), days[-1])


def test_numeric_times_step_on_their_grid():
    cal = RecordCalendar.of(np.arange(30.0) * 0.5)
    assert cal.next_stamp(14.5) == 15.0 and cal.next_stamp(15.1) == 15.5
    assert cal.same_period(15.1, 15.0) and not cal.same_period(15.3, 15.0)


def test_an_irregular_record_steps_from_the_time_itself():
    t = np.array([0.0, 1.0, 2.5, 3.0, 4.2, 6.0])
    cal = RecordCalendar.of(t, step=1.0)
    assert cal.kind == "irregular" and cal.next_stamp(6.3) == 7.3


def test_datetime_ns_refuses_dates_it_cannot_hold():
    assert datetime_ns("2262-04-10") == _ns("2262-04-10")
    assert datetime_ns("1678-01-01T06:00") == _ns("1678-01-01T06:00")
    for text in ("2800-03-01", "2500-01-15", "1600-01-01", "0001-01-01"):
        with pytest.raises(DataError, match=rf"--time {text} is outside .* 1677-09-21 to "
                                            r"2262-04-11"):
            datetime_ns(text, "--time")


# ----------------------------------------------------------------------------- properties
@st.composite
def monthly_records(draw):
    """A record stepping by ``n`` calendar months in one cftime calendar, stamped on one day of
    the month (and time of day) or at one fraction of the month."""
    calendar = draw(st.sampled_from(CALENDARS))
    n = draw(st.sampled_from([1, 1, 1, 3, 12]))
    size = draw(st.integers(3, 30))
    year = draw(st.integers(1, 2500))
    month0 = draw(st.integers(0, 11))
    hour = draw(st.sampled_from([0, 12]))
    by_fraction = draw(st.booleans())
    day = draw(st.integers(1, 28))
    times = []
    for i in range(size):
        y, m = divmod(month0 + i * n, 12)
        first = cftime.datetime(year + y, m + 1, 1, calendar=calendar)
        if by_fraction:
            dim = first.daysinmonth
            times.append(first + pd.Timedelta(seconds=round(0.5 * dim * 86400)).to_pytimedelta())
        else:
            times.append(first.replace(day=day, hour=hour))
    return calendar, n, np.asarray(times, dtype=object)


@settings(max_examples=40, deadline=None)
@given(monthly_records(), st.integers(0, 12), st.floats(0.0, 1.0))
def test_next_stamp_follows_every_monthly_record(record, ahead, where):
    calendar, n, times = record
    # stamps seen only in months of one length cannot tell a fixed day from a fraction of the
    # month (16 Dec 12:00 and 16 Jan 12:00 are both): the next stamp is then undetermined
    lengths = {t.daysinmonth for t in times}
    assume(len({t.daysinmonth for t in times[:-1]}) > 1 or len(lengths) == 1)
    cal = RecordCalendar.of(times[:-1])
    assert cal.kind == "months" and cal.n == n
    # the record's own next stamp, and each stamp is the stamp of its own period
    assert cal.next_stamp(times[-2]) == times[-1]
    assert all(cal.stamp_of(t) == t for t in times)
    # any time: its period's stamp is a stamp, the next stamp lies n months on and after it
    s = times[-1]
    for _ in range(ahead):
        s = cal.next_stamp(s)
    first = s.replace(day=1, hour=0)
    t = first + pd.Timedelta(days=where * (first.daysinmonth - 1)).to_pytimedelta()
    stamp = cal.stamp_of(t)
    nxt = cal.next_stamp(t)
    assert cal.same_period(t, stamp) and cal.stamp_of(stamp) == stamp
    assert cal.stamp_of(nxt) == nxt and nxt > stamp and not cal.same_period(nxt, stamp)
    assert (nxt.year * 12 + nxt.month) - (stamp.year * 12 + stamp.month) == n
    assert nxt.calendar == calendar


@settings(max_examples=40, deadline=None)
@given(st.sampled_from(CALENDARS), st.sampled_from([1, 2, 7]), st.integers(2, 40),
       st.integers(0, 23), st.integers(-3 * 1440, 60 * 1440))
def test_next_stamp_of_fixed_day_steps(calendar, step, size, hour, offset):
    start = cftime.datetime(2001, 3, 5, hour, calendar=calendar)
    times = np.asarray([start + pd.Timedelta(days=step * i).to_pytimedelta()
                        for i in range(size)], dtype=object)
    cal = RecordCalendar.of(times)
    assert cal.kind == "grid"
    assert all(cal.next_stamp(a) == b for a, b in zip(times[:-1], times[1:], strict=True))
    t = times[-1] + pd.Timedelta(minutes=offset).to_pytimedelta()
    stamp, nxt = cal.stamp_of(t), cal.next_stamp(t)
    assert cal.same_period(t, stamp) and nxt - stamp == pd.Timedelta(days=step)
    assert (stamp.hour, stamp.minute) == (hour, 0)
