"""What travels between processes: ``messages`` (msgpack schemas, validated on decode) and ``keys``
(every Zenoh key expression). Needs neither torch nor MuJoCo."""
