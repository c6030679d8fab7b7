// Numbers and requests as the page shows and makes them.

/// "4.6 km", "37 m", "2.5 m", "0.80 m", "3.2 cm", "4.0 mm": within 5 % of the value from 1 mm up,
/// and never "0.0 m" for a fine level of a rock-face scan.
export function formatMetres(metres) {
  if (metres === null || metres === undefined) {
    return 'n/a';
  }
  const size = Math.abs(metres);
  if (size >= 1000) {
    return `${(metres / 1000).toFixed(size >= 10000 ? 0 : 1)} km`;
  }
  if (size >= 0.1 || size === 0) {
    return `${metres.toFixed(size >= 10 ? 0 : size >= 1 ? 1 : 2)} m`;
  }
  if (size >= 0.01) {
    return `${(metres * 100).toFixed(1)} cm`;
  }
  return `${(metres * 1000).toFixed(size >= 0.001 ? 1 : 2)} mm`;
}

/// GET `path` from vsmd as JSON, never from a cache; throws on a status other than 2xx.
export async function getJson(path) {
  const response = await fetch(path, { cache: 'no-store' });
  if (!response.ok) {
    throw new Error(`GET ${path}: ${response.status}`);
  }
  return response.json();
}
