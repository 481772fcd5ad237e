"""ecas: a real-time, full-duplex embodied conversational agent in the manner of MIBURI, runnable on a CPU."""
