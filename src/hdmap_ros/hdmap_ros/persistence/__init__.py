"""SQLite stores that keep the live suite's drives and maps across restarts."""
