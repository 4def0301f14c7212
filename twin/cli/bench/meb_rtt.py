#!/usr/bin/env python3
# Usage: python3 twin/cli/bench/meb_rtt.py HOST:PORT   (a `twin supervise --listen` server, started
# with --rate-limit 100000 --open-loop 0 so the forwarded writes do not fight the loop)
# Round trips of MEB requests to a twin supervise server, and of a bare echo on loopback.
import socket, sys, time, threading, statistics
def fcs(b): 
    x=0
    for c in b.encode(): x^=c
    return "%02X"%x
def frame(body): return (body+fcs(body)+"*\n").encode()
def rtts(sock, req, n):
    out=[]; buf=b""
    for _ in range(n):
        t=time.perf_counter_ns(); sock.sendall(req)
        while b"\n" not in buf: buf+=sock.recv(4096)
        out.append((time.perf_counter_ns()-t)/1000); buf=buf[buf.index(b"\n")+1:]
    return out
def show(name, xs):
    xs=sorted(xs); print(f"  {name:34s} n={len(xs):5d} median {statistics.median(xs):8.1f} µs  p99 {xs[int(len(xs)*0.99)-1]:8.1f} µs")
host,port=sys.argv[1].split(":"); port=int(port)
s=socket.create_connection((host,port)); s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
rtts(s, frame("@01EA0006"), 200)
show("image read EA 00 06", rtts(s, frame("@01EA0006"), 5000))
show("loop mirror read FA 10 03", rtts(s, frame("@01FA1003"), 2000))
show("loop variable write VA 10 (local)", rtts(s, frame("@01VA100105DC"), 2000))
w=rtts(s, frame("@01SA00010000"), 300)
show("forwarded write SA 00 (over the bus)", w)
# bare echo on loopback, same client
ls=socket.socket(); ls.bind(("127.0.0.1",0)); ls.listen(1)
def echo():
    c,_=ls.accept(); c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    while True:
        d=c.recv(4096)
        if not d: break
        c.sendall(d)
threading.Thread(target=echo,daemon=True).start()
e=socket.create_connection(ls.getsockname()); e.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
rtts(e, frame("@01EA0006"), 200)
show("bare Python echo (same client)", rtts(e, frame("@01EA0006"), 5000))
