// Reads the Server-Sent Events of GET /events with fetch(), so that the bearer token travels
// in a header (an EventSource cannot send one). Reconnects after a pause when the stream ends.

const RETRY_MS = 2000;

export function openStream({ url, token, onBatch, onState }) {
  const ctrl = new AbortController();
  let closed = false;

  function handleBlock(block) {
    const data = block.split("\n").filter((l) => l.startsWith("data:"))
      .map((l) => l.slice(5).trimStart()).join("\n");
    if (data) onBatch(JSON.parse(data));
  }

  async function run() {
    while (!closed) {
      try {
        const headers = token ? { Authorization: `Bearer ${token}` } : {};
        const res = await fetch(url, { headers, signal: ctrl.signal, cache: "no-store" });
        if (!res.ok) {
          let msg = `${res.status}`;
          try { msg += `: ${(await res.json()).error}`; } catch { /* not JSON */ }
          onState("error", msg);
          if (res.status === 401 || res.status === 404) return;
        } else {
          onState("live", "live");
          const reader = res.body.pipeThrough(new TextDecoderStream()).getReader();
          let buf = "";
          for (;;) {
            const { value, done } = await reader.read();
            if (done) break;
            buf += value;
            let i;
            while ((i = buf.indexOf("\n\n")) >= 0) {
              handleBlock(buf.slice(0, i));
              buf = buf.slice(i + 2);
            }
          }
        }
      } catch (err) {
        if (closed) return;
        onState("error", String(err));
      }
      if (closed) return;
      onState("connecting", "reconnecting");
      await new Promise((r) => setTimeout(r, RETRY_MS));
    }
  }

  run();
  return { close() { closed = true; ctrl.abort(); } };
}
