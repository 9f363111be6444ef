"""Exports of a store to other tools' formats."""
