"""`phim loadtest`: simulated vehicles sending sectors at sensor rate (open loop) or as fast as answered
(closed loop), over HTTP or zenoh, with a sweep over the number of vehicles. See docs/protocol.md."""
