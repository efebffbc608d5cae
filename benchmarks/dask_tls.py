"""Start-up and per-task cost of the private (TLS) local Dask cluster of `tcspc flow run
--dask` against a plain one (docs/flows.md): `python benchmarks/dask_tls.py`."""

import time

from distributed import Client, LocalCluster, Security

if __name__ == "__main__":
    for name in ("plain", "tls", "plain", "tls"):
        kw = {"security": Security.temporary()} if name == "tls" else {}
        t = time.time()
        with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                          dashboard_address=None, **kw) as c:
            up = time.time() - t
            with Client(c) as cl:
                t2 = time.time()
                cl.gather(cl.map(lambda x: x + 1, range(500)))
                run = time.time() - t2
        print(name, f"start {up:.2f} s, 500 tasks {run:.2f} s", flush=True)
