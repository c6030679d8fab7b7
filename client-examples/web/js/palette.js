// The colours the viewer paints with.

import * as THREE from 'three';

/// sRGB colour per depth, 15 and deeper share the last: the same as kDepthPalette.
export const DEPTH_PALETTE = [
  '#30123b', '#4145ab', '#4675ed', '#39a2fc', '#1bcfd4', '#24eca6', '#61fc6c', '#a4fc3b',
  '#d1e834', '#f3c63a', '#fe9b2d', '#f36315', '#d93806', '#b11901', '#7a0402', '#4a0000',
];
/// The relief's grey (sRGB).
export const RELIEF_GREY = '#c8c8c8';
/// The diverging scale of the changes mode (sRGB): blue below, white unchanged, red above, in
/// CHANGE_BINS steps each way.
const CHANGE_LOW = [0x21, 0x66, 0xac];
const CHANGE_HIGH = [0xb2, 0x18, 0x2b];
export const CHANGE_BINS = 10;

export function paletteColour(depth) {
  return DEPTH_PALETTE[Math.min(depth, DEPTH_PALETTE.length - 1)];
}

/// The changes scale at t in [-1, 1] (linear colour).
export function changeColour(t) {
  const end = t < 0 ? CHANGE_LOW : CHANGE_HIGH;
  const a = Math.abs(t);
  return new THREE.Color(...end.map((c) => (255 + (c - 255) * a) / 255)).convertSRGBToLinear();
}
