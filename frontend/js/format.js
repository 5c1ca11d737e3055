// Units for people: the API speaks metres and seconds.

export const um = (m) => (m === null || m === undefined ? "—" : `${(m * 1e6).toFixed(3)} µm`);
export const nm = (m) => (m === null || m === undefined ? "—" : `${(m * 1e9).toFixed(2)} nm`);

export function duration(seconds) {
  if (!Number.isFinite(seconds) || seconds < 0) return "—";
  const s = Math.round(seconds);
  const h = Math.floor(s / 3600);
  const m = Math.floor((s % 3600) / 60);
  const r = s % 60;
  return h ? `${h} h ${m} min` : m ? `${m} min ${r} s` : `${r} s`;
}
