"""Measuring how well poses match the truth: metrics, tables, figures, reports and the demo."""
