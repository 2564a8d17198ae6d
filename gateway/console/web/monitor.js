// The bus monitor (docs/MONITOR.md): the decoded frames of one bus, live. The gateway filters by
// servo and kind; pausing only stops drawing (frames overwritten meanwhile come back as `dropped`).
import { header, live, say, element } from '/static/console.js';

await header('monitor');
const bus = decodeURIComponent(location.pathname.split('/')[2] || '');
document.getElementById('title').textContent = `Bus monitor — ${bus}`;
document.title = `sms-gateway — ${bus} monitor`;
document.getElementById('download').href = `/api/bus/${encodeURIComponent(bus)}/monitor.pcapng`;

const kMaxRows = 500;  // the page keeps the newest rows; the capture download has the whole ring
const body = document.querySelector('#frames tbody');
let paused = false, shown = 0, dropped = 0;

function time(us) {
  const date = new Date(us / 1000);
  return date.toTimeString().slice(0, 8) + '.' + String(us % 1000000).padStart(6, '0');
}

function fields(frame) {
  return (frame.fields || []).map((f) => (f.servo !== undefined ? `[${f.servo}] ` : '') + f.name +
    (f.value !== undefined ? '=' + f.value : '')).join(', ');
}

function row(frame) {
  const bad = frame.kind === 'damaged' || frame.kind === 'noise' || frame.error;
  return element('tr', { class: 'frame ' + frame.kind, 'data-kind': frame.kind, 'data-servo': frame.servo ?? '' },
    element('td', { class: 'num' }, time(frame.time_us)),
    element('td', {}, frame.dir === 'to_servos' ? '→' : '←'),
    element('td', { class: 'num' }, frame.servo ?? ''),
    element('td', { class: bad ? 'bad' : '' }, frame.kind + (frame.retry ? ' (retry)' : '')),
    element('td', { class: 'instruction' }, frame.instruction || ''),
    element('td', { class: 'fields' }, fields(frame)),
    element('td', {}, (frame.status_bits || []).join(', ')),
    element('td', { class: 'bad' }, frame.error || ''),
    element('td', { class: 'muted bytes', title: frame.bytes || '' }, frame.bytes || ''));
}

function counts() {
  document.getElementById('counts').textContent =
    `${shown} frames shown` + (dropped ? `, ${dropped} records missed (the browser fell behind)` : '') + (paused ? ' — paused' : '');
}

const socket = live(`/ws/bus/${encodeURIComponent(bus)}/monitor`, (batch) => {
  if (batch.error) return say(batch.error, 'error');
  dropped += batch.dropped || 0;
  if (!paused) {
    for (const frame of batch.frames) body.prepend(row(frame));
    shown += batch.frames.length;
    while (body.rows.length > kMaxRows) body.deleteRow(-1);
  }
  counts();
}, () => sendFilter());

function sendFilter() {
  const servo = document.getElementById('servo').value;
  socket.send({
    servo: servo === '' ? null : Number(servo),
    requests: document.getElementById('requests').checked,
    answers: document.getElementById('answers').checked,
    errors: document.getElementById('errors').checked,
  });
}
for (const id of ['servo', 'requests', 'answers', 'errors']) document.getElementById(id).addEventListener('change', sendFilter);
document.getElementById('pause').addEventListener('click', (event) => {
  paused = !paused;
  event.target.textContent = paused ? 'Resume' : 'Pause';
  counts();
});
document.getElementById('clear').addEventListener('click', () => { body.replaceChildren(); shown = 0; counts(); });
counts();
