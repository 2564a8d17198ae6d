import { header, live, api, say, element, setEstop, allows } from '/static/console.js';

const unit = Number(location.pathname.split('/').pop());
const me = await header('servo');
const canOperate = allows(me.role, 'operate');
const canEngineer = allows(me.role, 'engineer');
live('/ws/overview', (data) => setEstop(data.gateway.estop.latched));

// --- control table ------------------------------------------------------------------------------
let servo = null;
const valueCells = new Map();

function rangeText(field) {
  return field.allowed.length ? field.allowed.join(', ') : `${field.min}..${field.max}`;
}

async function write(field, input) {
  const value = Number(input.value);
  if (input.value.trim() === '' || !Number.isInteger(value)) return say(`${field.name}: enter an integer`, 'error');
  if (value < field.min || value > field.max) return say(`${field.name}: ${value} is outside ${field.min}..${field.max}; nothing written`, 'error');
  if (field.allowed.length && !field.allowed.includes(value)) return say(`${field.name}: ${value} is not one of ${field.allowed.join(', ')}`, 'error');
  if (field.area === 'EEPROM' && !confirm(`Write ${field.name} := ${value} to EEPROM (kept over power-off)?`)) return;
  try {
    await api('POST', `/api/servo/${unit}/write`, { field: field.name, value });
    say(`${field.name} := ${value} written`, 'done');
    await load();
  } catch (error) { say(error.message, 'error'); }
}

function editCell(field) {
  if (!field.writable) return element('td', { class: 'muted' }, field.access === 'R' ? 'read-only' : '');
  if (field.commissioning) return element('td', { class: 'muted' }, 'set-id / set-baud');
  const allowed = field.engineer ? canEngineer : canOperate;
  if (!allowed) return element('td', { class: 'muted' }, field.engineer ? 'needs engineer' : 'needs operate');
  const input = element('input', { class: 'edit', type: 'number', min: field.min, max: field.max });
  const button = element('button', { class: 'write' }, 'Write');
  button.addEventListener('click', () => write(field, input));
  input.addEventListener('keydown', (event) => { if (event.key === 'Enter') write(field, input); });
  return element('td', {}, input, ' ', button);
}

async function load() {
  servo = await api('GET', `/api/servo/${unit}`);
  document.title = `sms-gateway — unit ${unit}`;
  document.getElementById('title').textContent =
    `Unit ${servo.unit} — servo ${servo.id} on bus ${servo.bus} (${servo.map})${servo.name ? ' — ' + servo.name : ''}`;
  if (servo.values_error) say('reading the table: ' + servo.values_error, 'error');
  valueCells.clear();
  document.querySelector('#fields-table tbody').replaceChildren(...servo.fields.map((field) => {
    const value = element('td', { class: 'num value' }, servo.values[field.name] ?? '');
    valueCells.set(field.name, value);
    return element('tr', { id: 'field-' + field.name, class: field.polled ? 'polled' : '' },
      element('td', {}, field.name), element('td', { class: 'num' }, field.address), element('td', {}, field.unit),
      element('td', {}, rangeText(field)), element('td', {}, field.area), element('td', {}, field.access), value, editCell(field));
  }));
  const goal = servo.fields.find((f) => f.name === 'goal_position');
  const range = document.getElementById('jog-position-range');
  if (goal) { range.min = goal.min; range.max = goal.max; }
  if (!plotFields.length) setupPlotFields();
}
document.getElementById('refresh').addEventListener('click', load);

// --- plot ---------------------------------------------------------------------------------------
const plotFields = [];
const COLOURS = ['#1f5fbf', '#b42318', '#1b7f3b', '#b54708', '#6941c6', '#0e7090', '#c11574', '#667085'];
const history = [];      // [time_s, {field: value}] for every sample, last 60 s
let fieldNames = [];
let paused = false;
let shown = [];          // the rows on the plot now: what the CSV export writes (paused: the frozen window)
const chart = new Chart(document.getElementById('plot'), {
  type: 'line',
  data: { datasets: [] },
  options: { animation: false, parsing: false, normalized: true, maintainAspectRatio: false,
    scales: { x: { type: 'linear', title: { display: true, text: 's' } } },
    elements: { point: { radius: 0 } } },
});

function setupPlotFields() {
  const wanted = ['present_position', 'present_speed', 'present_load', 'present_current', 'present_temperature', 'present_voltage'];
  const box = document.getElementById('plot-fields');
  for (const field of servo.fields.filter((f) => f.polled && f.readable)) {
    const on = field.name === 'present_position';
    if (!wanted.includes(field.name) && !on) continue;
    const box_ = element('input', { type: 'checkbox', id: 'plot-' + field.name });
    box_.checked = on;
    box_.addEventListener('change', redraw);
    box.append(element('label', {}, box_, ' ' + field.name));
    plotFields.push(field.name);
  }
}

function selected() { return plotFields.filter((name) => document.getElementById('plot-' + name).checked); }
function windowSeconds() { return Number(document.getElementById('window').value); }

function plotted() {
  if (!history.length) return [];
  const end = history[history.length - 1][0];
  return history.filter(([t]) => t >= end - windowSeconds());
}

function redraw() {
  const rows = plotted();
  shown = rows;
  chart.data.datasets = selected().map((name, i) => ({
    label: name, borderColor: COLOURS[i % COLOURS.length], borderWidth: 1.5,
    data: rows.filter(([, v]) => name in v).map(([t, v]) => ({ x: t, y: v[name] })) }));
  chart.update('none');
  document.getElementById('plot-count').textContent = `${rows.length} samples`;
  document.getElementById('plot').dataset.samples = String(rows.length);
}

document.getElementById('pause').addEventListener('click', (event) => {
  paused = !paused;
  event.target.textContent = paused ? 'Resume' : 'Pause';
  if (!paused) redraw();
});
document.getElementById('window').addEventListener('change', redraw);
document.getElementById('csv').addEventListener('click', () => {
  const names = selected();
  const lines = ['time_s,' + names.join(',')];
  for (const [t, v] of shown) lines.push([t.toFixed(4), ...names.map((n) => v[n] ?? '')].join(','));
  const link = element('a', { href: URL.createObjectURL(new Blob([lines.join('\n') + '\n'], { type: 'text/csv' })),
    download: `unit${unit}-plot.csv` });
  document.body.append(link);
  link.click();
  link.remove();
});

let t0 = null;
function onSamples(message) {
  if (message.type === 'error') return say(message.message, 'error');
  if (message.type === 'done') return say(message.message, 'done');
  // The gateway ended the held move (e-stop, watchdog, no heartbeat): let go of the hold, so
  // moving again takes a new press.
  if (message.type === 'jog_ended') {
    stopHold();
    return say(message.message, 'error');
  }
  if (message.type !== 'samples') return;
  fieldNames = message.fields;
  for (const row of message.samples) {
    if (t0 === null) t0 = row[0];
    const values = {};
    fieldNames.forEach((name, i) => { values[name] = row[i + 1]; });
    history.push([(row[0] - t0) / 1e6, values]);
  }
  while (history.length && history[history.length - 1][0] - history[0][0] > 60) history.shift();
  const last = history[history.length - 1];
  if (last) for (const [name, value] of Object.entries(last[1])) {
    const cell = valueCells.get(name);
    if (cell) cell.textContent = value;
  }
  const state = document.getElementById('jog-state');
  state.textContent = message.jog === 'stopped' ? `stopped${message.jog_reason ? ' (' + message.jog_reason + ')' : ''}` : 'moving (' + message.jog + ')';
  if (!paused) redraw();
}

await load();
const stream = live(`/ws/servo/${unit}`, onSamples);

// --- jog panel: hold-to-run -------------------------------------------------------------------------
// While a hold button is down the page sends a heartbeat every 50 ms; the gateway stops the servo
// when they stop coming (released, tab closed, connection lost), and ends the move for good on an
// e-stop or a watchdog trip (docs/CONSOLE.md "Jog panel").
let heartbeat = null;
function startHold(button, message) {
  if (heartbeat) return;
  button.classList.add('active');
  stream.send(message);
  heartbeat = setInterval(() => stream.send({ type: 'heartbeat' }), 50);
}
function stopHold() {
  if (!heartbeat) return;
  clearInterval(heartbeat);
  heartbeat = null;
  document.querySelectorAll('.hold').forEach((b) => b.classList.remove('active'));
  stream.send({ type: 'release' });
}
function holdButton(id, message) {
  const button = document.getElementById(id);
  button.disabled = !canOperate;
  button.addEventListener('pointerdown', (event) => { button.setPointerCapture(event.pointerId); startHold(button, message()); });
  button.addEventListener('pointerup', stopHold);
  button.addEventListener('pointercancel', stopHold);
  button.addEventListener('lostpointercapture', stopHold);
}
const position = document.getElementById('jog-position');
const positionRange = document.getElementById('jog-position-range');
positionRange.addEventListener('input', () => { position.value = positionRange.value; });
position.addEventListener('input', () => { positionRange.value = position.value; });
holdButton('hold-position', () => ({ type: 'jog', mode: 'position', value: Number(position.value) }));
holdButton('hold-speed', () => ({ type: 'jog', mode: 'speed', value: Number(document.getElementById('jog-speed').value) }));
window.addEventListener('blur', stopHold);
for (const [id, on] of [['torque-on', true], ['torque-off', false]]) {
  const button = document.getElementById(id);
  button.disabled = !canOperate;
  button.addEventListener('click', () => stream.send({ type: 'torque', on }));
}
if (!canOperate) document.getElementById('jog-note').textContent = 'The jog panel needs the operate role.';
