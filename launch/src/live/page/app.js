// The live page: draws /state.json snapshots (the first inlined in the page, the rest pushed
// as server-sent events on /events). No polling, no third-party code.
'use strict';

const SVGNS = 'http://www.w3.org/2000/svg';
const $ = (id) => document.getElementById(id);

function num(v, digits) {
  return v === null || v === undefined || !isFinite(v) ? '-' : Number(v).toFixed(digits);
}

function duration(s) {
  if (s === null || s === undefined || !isFinite(s)) return '-';
  s = Math.round(s);
  return s >= 60 ? `${Math.floor(s / 60)}m${String(s % 60).padStart(2, '0')}s` : `${s}s`;
}

function svg(name, attrs) {
  const e = document.createElementNS(SVGNS, name);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
  return e;
}

function cell(row, text, cls) {
  const td = row.insertCell();
  td.textContent = text;
  if (cls) td.className = cls;
  return td;
}

const PLACEMENT = { registration: 'registration', weak_link: 'weak link', stage_fallback: 'stage fallback' };

// The preview PNG is fetched (not reloaded by the page) when the canvas changed; its headers
// say where it lies and which heights its colours span.
let previewShown = -1;
let previewLoading = false;
let previewUrl = null;
function refreshPreview(s) {
  if (!s.canvas || s.canvas.version === previewShown || previewLoading) return;
  previewLoading = true;
  const version = s.canvas.version;
  fetch('/preview.png', { cache: 'no-store' })
    .then((r) => {
      if (!r.ok) throw new Error(r.status);
      const range = (r.headers.get('X-Height-Range-Um') || '').split(' ').map(Number);
      const extent = (r.headers.get('X-Extent-Um') || '').split(' ').map(Number);
      return r.blob().then((b) => ({ b, range, extent }));
    })
    .then(({ b, range, extent }) => {
      if (previewUrl) URL.revokeObjectURL(previewUrl);
      previewUrl = URL.createObjectURL(b);
      const img = $('preview');
      img.setAttribute('href', previewUrl);
      if (extent.length === 4) {
        img.setAttribute('x', extent[0]);
        img.setAttribute('y', extent[1]);
        img.setAttribute('width', extent[2]);
        img.setAttribute('height', extent[3]);
      }
      if (range.length === 2) {
        $('scale-lo').textContent = num(range[0], 3);
        $('scale-hi').textContent = num(range[1], 3);
      }
      $('preview-note').textContent = 'panorama preview (decimated), updated per placed tile';
      previewShown = version;
    })
    .catch(() => {})
    .finally(() => {
      previewLoading = false;
      if (state.canvas && state.canvas.version !== previewShown) refreshPreview(state);
    });
}

function drawGrid(s) {
  const boxes = $('boxes');
  const planned = $('planned-boxes');
  boxes.replaceChildren();
  planned.replaceChildren();
  let x0 = Infinity, y0 = Infinity, x1 = -Infinity, y1 = -Infinity;
  const grow = (x, y, w, h) => {
    x0 = Math.min(x0, x); y0 = Math.min(y0, y); x1 = Math.max(x1, x + w); y1 = Math.max(y1, y + h);
  };
  if (s.canvas) grow(s.canvas.x0_um, s.canvas.y0_um, s.canvas.width_um, s.canvas.height_um);
  for (const t of s.tiles) {
    const w = t.width_um, h = t.height_um;
    if (w === null || h === null) continue;
    const rc = t.row === null ? '' : ` (row ${t.row} x col ${t.col})`;
    if (t.stage_x_um !== null) {
      grow(t.stage_x_um, t.stage_y_um, w, h);
      const p = svg('rect', { class: 'planned', x: t.stage_x_um, y: t.stage_y_um, width: w, height: h, 'data-planned': t.index });
      planned.appendChild(p);
    }
    if (t.x_um === null) continue;
    grow(t.x_um, t.y_um, w, h);
    const r = svg('rect', { class: `tile ${t.placement}`, x: t.x_um, y: t.y_um, width: w, height: h, 'data-tile': t.index });
    const title = svg('title', {});
    title.textContent = `tile ${t.index}${rc}: ${PLACEMENT[t.placement] || t.placement}, NCC ${num(t.ncc, 3)}\n`
      + `registered (${num(t.x_um, 2)}, ${num(t.y_um, 2)}) um${t.final_solve ? ' (end-of-scan solve)' : ''}\n`
      + `planned (${num(t.stage_x_um, 2)}, ${num(t.stage_y_um, 2)}) um`;
    r.appendChild(title);
    boxes.appendChild(r);
    const label = svg('text', { class: 'label', x: t.x_um + w / 2, y: t.y_um + h / 2, 'text-anchor': 'middle' });
    label.textContent = t.index;
    boxes.appendChild(label);
  }
  if (isFinite(x0)) {
    const m = 0.03 * Math.max(x1 - x0, y1 - y0);
    $('grid').setAttribute('viewBox', `${x0 - m} ${y0 - m} ${x1 - x0 + 2 * m} ${y1 - y0 + 2 * m}`);
    // Labels a fixed share of the view.
    for (const l of boxes.querySelectorAll('text')) l.setAttribute('font-size', 0.03 * (x1 - x0));
  }
}

function drawTables(s) {
  const tb = $('tiles').tBodies[0];
  tb.replaceChildren();
  for (const t of s.tiles) {
    const r = tb.insertRow();
    r.dataset.index = t.index;
    cell(r, t.index);
    cell(r, t.row === null ? '?' : `${t.row} x ${t.col}`);
    cell(r, t.stage_x_um === null ? '-' : `${num(t.stage_x_um, 2)}, ${num(t.stage_y_um, 2)}`);
    cell(r, t.x_um === null ? '-' : `${num(t.x_um, 2)}, ${num(t.y_um, 2)}`);
    cell(r, t.placement ? PLACEMENT[t.placement] + (t.final_solve ? ' (final)' : '') : '-', `placement-${t.placement}`);
    cell(r, num(t.ncc, 3));
    cell(r, num(t.tile_to_panorama_ms, 1));
  }
  const pb = $('pairs').tBodies[0];
  pb.replaceChildren();
  for (const p of s.pairs) {
    const r = pb.insertRow();
    r.dataset.pair = `${p.a}-${p.b}`;
    r.dataset.weak = p.weak_link;
    r.dataset.layout = p.layout_inconsistent;
    cell(r, `${p.a}-${p.b}`);
    cell(r, p.direction);
    cell(r, num(p.ncc, 3));
    cell(r, p.residual_px === null ? '-' : num(p.residual_px, 3) + (p.residual_of === 'global_solve' ? ' (solve)' : ' (streaming)'));
    cell(r, p.offset_px ? `${num(p.offset_px[0] - p.nominal_offset_px[0], 2)}, ${num(p.offset_px[1] - p.nominal_offset_px[1], 2)}` : '-');
    const outcome = !p.accepted ? `refused${p.reason ? ': ' + p.reason : ''}`
      : p.layout_inconsistent ? 'INCONSISTENT with the layout (check --serpentine / --overlap)'
      : p.weak_link ? 'weak link' : p.kept_by_global_solve === false ? 'dropped by the solve' : 'accepted';
    cell(r, outcome, p.weak_link ? 'placement-weak_link' : !p.accepted || p.layout_inconsistent ? 'placement-stage_fallback' : '');
  }
  const final = s.pairs.some((p) => p.final_solve);
  $('pairs-note').textContent = !s.pairs.length ? 'no pair decided yet'
    : final ? 'after the end-of-scan solve (the matcher\'s report)'
    : 'as the matcher decides them; residuals from the streaming placement until the end-of-scan solve';
}

function render(s) {
  $('graph').textContent = s.graph ? `: ${s.graph}` : '';
  const v = $('verdict');
  v.className = `badge ${s.verdict || 'running'}`;
  v.textContent = s.verdict || (s.scan_ended ? 'scan done, final passes running' : 'running');
  document.body.dataset.verdict = s.verdict || '';
  document.body.dataset.tilesRegistered = s.tiles_registered;
  $('done').textContent = s.tiles_registered;
  $('planned').textContent = s.tiles_planned === null ? '?' : s.tiles_planned;
  const p = s.progress;
  $('pace').textContent = num(p.fields_per_s, 2);
  $('eta').textContent = duration(p.eta_s);
  const l = p.tile_to_panorama_ms;
  $('latency').textContent = l.n ? `${num(l.newest, 1)} ms newest, p50 ${num(l.p50, 1)} ms, max ${num(l.max, 1)} ms` : '-';
  const d = s.drops;
  const dropped = d.preview_patches_missed + d.page_updates_skipped + d.foxglove_messages_skipped;
  $('drops').textContent = dropped ? `view skipped: ${d.preview_patches_missed} preview patches, `
    + `${d.page_updates_skipped} page updates, ${d.foxglove_messages_skipped} Foxglove messages` : '';
  drawGrid(s);
  drawTables(s);
  const st = $('stages');
  st.replaceChildren();
  for (const line of s.stages) {
    const li = document.createElement('li');
    li.textContent = line.text;
    li.className = `ok-${line.ok}`;
    st.appendChild(li);
  }
  $('verdict-text').textContent = s.verdict_text || (s.run_ended ? '' : 'the verdict comes when the run ends');
  $('report').hidden = !s.report;
  $('stop').hidden = !(s.stop_allowed && !s.run_ended);
  refreshPreview(s);
}

let state = JSON.parse($('initial-state').textContent);
render(state);

if (window.EventSource) {
  const events = new EventSource('/events');
  events.addEventListener('state', (e) => {
    state = JSON.parse(e.data);
    render(state);
    if (state.run_ended && state.verdict) events.close();
  });
}

$('stop').addEventListener('click', () => {
  if (!confirm('Stop the run? Its out dir will hold a FAILED record.')) return;
  fetch('/stop', { method: 'POST' }).then((r) => r.text()).then((t) => { $('stop').textContent = t; });
});

$('show-tile').addEventListener('click', () => {
  fetch('/tile.png', { cache: 'no-store' })
    .then((r) => {
      if (!r.ok) throw new Error(`${r.status}`);
      const range = (r.headers.get('X-Height-Range-Um') || '').split(' ').map(Number);
      const index = r.headers.get('X-Tile-Index');
      return r.blob().then((b) => ({ b, range, index }));
    })
    .then(({ b, range, index }) => {
      const img = $('tile-img');
      if (img.src) URL.revokeObjectURL(img.src);
      img.src = URL.createObjectURL(b);
      $('tile-note').textContent = `tile ${index}, every pixel; colours ${num(range[0], 3)} to ${num(range[1], 3)} um`;
      $('tile-view').hidden = false;
    })
    .catch((e) => { $('tile-note').textContent = `no tile yet (${e.message})`; $('tile-view').hidden = false; });
});
