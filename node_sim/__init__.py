"""taxel-can node firmware twin: CANopen taxel nodes (local detector, OD, NMT, PDO, heartbeat, EMCY)."""
