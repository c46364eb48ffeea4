"""The cache folder as the API keeps it: a run's working stores, its dictionaries and the report's records
(``codedvideo cache verify`` and ``clean``), and the keys records are filed under."""

from __future__ import annotations

from codedvideo.engine.cache import clean_cache, content_key, report_record_problem, verify_cache

__all__ = ["clean_cache", "content_key", "report_record_problem", "verify_cache"]
