"""How late the latency poll saw the 1 % of events it saw latest (session 19, late_polls.md).

Input: a pickle written at the end of `run_once` by a temporary patch (not kept) of
`mapservice/bench/ingest.py`: {"keys": published key -> publish wall time, "first_seen",
"not_seen_at", "received_at" (the poller's dicts), "pushed_at" (the live listener's),
"log": one (kind, asked_at, seen_at, from_ms, to_ms, rows) per poll}.
Usage: python late_polls.py DUMP.pkl
"""
import pickle, json, sys, statistics, bisect
d=pickle.load(open(sys.argv[1],'rb'))
keys=d['keys']; fs=d['first_seen']; ns=d['not_seen_at']; pa=d['pushed_at']; log=d['log']
rows=sorted((fs[k]-w, k, w) for k,w in keys.items() if k in fs)
n=len(rows); late=rows[int(n*0.99):]
print('n',n,'p99 polled %.3f'%late[0][0])
pl=sorted(pa[k]-w for _,k,w in late if k in pa)
print('late events (top 1%%): push latency median %.3f p90 %.3f max %.3f n %d'%(statistics.median(pl), pl[int(len(pl)*.9)], max(pl), len(pl)))
gap=sorted(fs[k]-pa[k] for _,k,w in late if k in pa)
print('late: first_seen - pushed: median %.3f p10 %.3f'%(statistics.median(gap), gap[len(gap)//10]))
bykind={}
for e in log: bykind.setdefault(e[0],[]).append(e)
for kk,v in bykind.items():
    dur=sorted(s-a for _,a,s,*_ in v); rws=sorted(x[5] for x in v)
    print(kk,'polls',len(v),'dur p50 %.3f p99 %.3f max %.3f'%(dur[len(dur)//2],dur[int(len(dur)*.99)],dur[-1]),'rows p50',rws[len(rws)//2],'max',rws[-1])
# classify each late event: the first poll asked after its push -> did it return it?
cats={'poll after push returned it':0,'poll after push missed it':0,'no push':0}
waits=[]
for _,k,w in late:
    p=pa.get(k)
    if p is None: cats['no push']+=1; continue
    v=bykind[k[0]]; asks=[x[1] for x in v]
    i=bisect.bisect_right(asks,p)
    if i<len(v):
        x=v[i]
        if abs(x[2]-fs[k])<1e-9: cats['poll after push returned it']+=1; waits.append((x[1]-p, x[2]-x[1]))
        else: cats['poll after push missed it']+=1
print(cats)
if waits:
    a=sorted(w[0] for w in waits); b=sorted(w[1] for w in waits)
    print('late: wait from push to next poll ask: median %.3f p90 %.3f; that poll took median %.3f p90 %.3f'%(a[len(a)//2],a[int(len(a)*.9)],b[len(b)//2],b[int(len(b)*.9)]))
# timeline of poll durations: biggest
big=sorted(log,key=lambda e:e[2]-e[1])[-8:]
t0=min(keys.values())
for e in big: print(e[0],'at +%.1f took %.3f rows %d window %.1fs'%(e[1]-t0,e[2]-e[1],e[5],(e[4]-e[3])/1000))
