"""What a benchmark process holds, read from Linux's /proc: its resident and peak memory, the pages of files it
maps, and the machine's load (bench_eval.py prints them beside each case: the CPU may be shared)."""
import os


def status_mib(field):
    """A field of /proc/self/status (VmRSS, VmHWM, RssAnon, RssFile...) in MiB; nan where it is absent."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024  # kB -> MiB
    return float("nan")


def reset_peak():
    """Reset VmHWM to the current RSS (Linux >= 4.0); returns False where that is not allowed."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def load_average():
    with open("/proc/loadavg") as f:
        return " ".join(f.read().split()[:3])


def mapped_rss(folder):
    """MiB resident of the files mapped from `folder`, by suffix (/proc/self/smaps): the codes (.faiss) and the
    float16 rows (.f16); capped at the files' sizes, since a file mapped several times counts its pages in each
    mapping."""
    out, suffix = {".faiss": 0.0, ".f16": 0.0}, None
    with open("/proc/self/smaps") as f:
        for line in f:
            head = line.split()
            if len(head) >= 6 and "-" in head[0]:  # a mapping's first line ends with its path
                suffix = next((s for s in out if head[-1].startswith(folder) and head[-1].endswith(s)), None)
            elif suffix and line.startswith("Rss:"):
                out[suffix] += int(head[1]) / 1024
    sizes = {s: sum(os.path.getsize(os.path.join(folder, f)) for f in os.listdir(folder) if f.endswith(s)) / 2**20
             for s in out}
    return {s: min(out[s], sizes[s]) for s in out}
