"""Lamp IDs carried by fast brightness switching, read through a rolling shutter."""
