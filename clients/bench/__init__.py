"""`phim bench server` and the bare responder that measures its transport floor."""
