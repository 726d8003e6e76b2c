"""Temporal control: filters as data, the loop delay model, RTC matrix assembly."""
