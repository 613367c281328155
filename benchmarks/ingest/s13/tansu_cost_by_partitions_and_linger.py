"""tansu's CPU per event against partitions and producer linger (session 13, BENCHMARKS.md).

A keyed, idempotent producer (as the gateway's) sends RATE records/s of 300 bytes to one
topic of P partitions with linger.ms L; a consumer (fetch wait FW ms) reads them all. Prints
tansu's CPU over SECS seconds and the produce -> consume lag. Run from the repository with
its venv, e.g. `P=1 L=20 RATE=6000 .venv/bin/python benchmarks/ingest/s13/tansu_cost_by_partitions_and_linger.py`.
"""
import os, random, threading, time
import psutil
from confluent_kafka import Producer, Consumer
from confluent_kafka.admin import AdminClient, NewTopic
from mapservice.local import embedded

P = int(os.environ.get("P", "6")); L = int(os.environ.get("L", "50"))
RATE = int(os.environ.get("RATE", "1200")); SECS = float(os.environ.get("SECS", "20"))
FW = int(os.environ.get("FW", "50"))
port = embedded.free_port()
proc = embedded.start_tansu(port, open(os.devnull, "w"))
try:
    bs = f"127.0.0.1:{port}"
    time.sleep(1.5)
    adm = AdminClient({"bootstrap.servers": bs}); adm.create_topics([NewTopic("t", P, 1)])["t"].result()
    p = Producer({"bootstrap.servers": bs, "linger.ms": L, "enable.idempotence": True, "acks": "all",
                  "partitioner": "murmur2_random"})
    c = Consumer({"bootstrap.servers": bs, "group.id": "g", "fetch.wait.max.ms": FW,
                  "auto.offset.reset": "earliest", "enable.auto.commit": False})
    from confluent_kafka import TopicPartition
    c.assign([TopicPartition("t", i, 0) for i in range(P)])
    got = [0]; lags = []; stop = False
    def reader():
        while not stop:
            first = c.poll(0.05)
            if first is None:
                continue
            for m in [first, *c.consume(999, 0)]:
                if not m.error():
                    got[0] += 1
                    lags.append(time.time() * 1000 - m.timestamp()[1])
    t = threading.Thread(target=reader); t.start()
    time.sleep(3)
    payload = b"x" * 300
    tp = psutil.Process(proc.pid)
    c0 = sum(tp.cpu_times()[:2]); t0 = time.monotonic(); n = 0
    while time.monotonic() - t0 < SECS:
        target = int((time.monotonic() - t0) * RATE)
        while n < target:
            p.produce("t", key=f"robot-{random.randrange(1000)}".encode(), value=payload); n += 1
        p.poll(0); time.sleep(0.002)
    p.flush()
    c1 = sum(tp.cpu_times()[:2]); wall = time.monotonic() - t0
    time.sleep(1); stop = True; t.join()
    lags = sorted(lags[len(lags)//10:])
    q = lambda x: lags[int(x * (len(lags) - 1))]
    print(f"P={P} L={L} FW={FW} rate={RATE}: tansu {100*(c1-c0)/wall:.1f} % of a core, {1e6*(c1-c0)/n:.0f} us/event; "
          f"got {got[0]}/{n}; produce->consume lag p50 {q(.5):.0f} p99 {q(.99):.0f} ms")
finally:
    proc.terminate(); proc.wait()
