"""Validated choices: candidates scored on held-out parts of a record, one rule, one table.

Every ``"auto"`` setting is a specification of the one search of :mod:`.search`.
"""
