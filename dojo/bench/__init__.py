"""`dojo bench`: throughput and parity measurements, each printing one JSON line with its baseline."""
