"""Browser tests of the web page (service/static/)."""
