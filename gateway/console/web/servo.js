import { header, live, api, say, element, allows, onOverview, scaled, withUnit } from '/static/console.js';

const unit = Number(location.pathname.split('/').pop());
const me = await header('servo');
const canOperate = allows(me.role, 'operate');
const canEngineer = allows(me.role, 'engineer');

// --- control table ------------------------------------------------------------------------------
let servo = null;
const valueCells = new Map();

function rangeText(field) {
  const raw = field.allowed.length ? field.allowed.join(', ') : `${field.min}..${field.max}`;
  if (!field.scale || field.allowed.length || (field.scale.scale === 1)) return raw;
  return `${raw} (${withUnit(field.min, field.scale)} .. ${withUnit(field.max, field.scale)})`;
}

// Writes take the raw register value (the API's `value`, as a Modbus client writes it); the box
// says so and shows what the number means in the field's unit while it is typed.
async function write(field, input) {
  const value = Number(input.value);
  if (input.value.trim() === '' || !Number.isInteger(value)) return say(`${field.name}: enter the raw register value (an integer)`, 'error');
  if (value < field.min || value > field.max) return say(`${field.name}: ${value} is outside ${field.min}..${field.max}; nothing written`, 'error');
  if (field.allowed.length && !field.allowed.includes(value)) return say(`${field.name}: ${value} is not one of ${field.allowed.join(', ')}`, 'error');
  if (field.area === 'EEPROM' && !confirm(`Write ${field.name} := ${value} to EEPROM (kept over power-off)?`)) return;
  const shown = field.scale && field.scale.scale !== 1 ? ` (${withUnit(value, field.scale)})` : '';
  // Watched from before it is sent: a trip during the request counts as one after the write.
  watchMove(`${field.name} := ${value}${shown}`, field.name === 'goal_position' ? value : null);
  try {
    await api('POST', `/api/servo/${unit}/write`, { field: field.name, value });
    say(`${field.name} := ${value}${shown} written`, 'done');
    await load();
  } catch (error) {
    move = null;  // refused: nothing of this page's moves
    say(error.message, 'error');
  }
}

function editCell(field) {
  if (!field.writable) return element('td', { class: 'muted' }, field.access === 'R' ? 'read-only' : '');
  if (field.commissioning) return element('td', { class: 'muted' }, 'set-id / set-baud');
  const allowed = field.engineer ? canEngineer : canOperate;
  if (!allowed) return element('td', { class: 'muted' }, field.engineer ? 'needs engineer' : 'needs operate');
  const input = element('input', { class: 'edit', type: 'number', min: field.min, max: field.max, placeholder: 'raw',
    title: `the raw register value, ${field.min}..${field.max}` + (field.unit ? ` (table unit: ${field.unit})` : '') });
  const meaning = element('span', { class: 'meaning muted' }, '');
  input.addEventListener('input', () => {
    const value = Number(input.value);
    meaning.textContent = field.scale && field.scale.scale !== 1 && input.value.trim() !== '' && Number.isFinite(value) ? '= ' + withUnit(value, field.scale) : '';
  });
  const button = element('button', { class: 'write' }, 'Write');
  button.addEventListener('click', () => write(field, input));
  input.addEventListener('keydown', (event) => { if (event.key === 'Enter') write(field, input); });
  return element('td', {}, input, ' ', button, ' ', meaning);
}

const fieldsByName = new Map();
function showValue(name, raw) {
  const cells = valueCells.get(name);
  if (!cells) return;
  const field = fieldsByName.get(name);
  cells[0].textContent = withUnit(raw, field && field.scale);
  cells[1].textContent = raw ?? '';
}

// The jog slider spans what the servo may be driven to: the goal's range, narrowed to the
// servo's angle limits where the table has them (both 0: multi-turn, the field's range), by the
// names the gateway gives for this table (servo.motion: d55d's are cw/ccw_angle_limit).
function setupJogRange() {
  const goal = servo.fields.find((f) => f.name === servo.motion.goal_position);
  if (!goal) return;
  let min = goal.min, max = goal.max, from = goal.name;
  const low = servo.values[servo.motion.min_limit], high = servo.values[servo.motion.max_limit];
  if (low !== undefined && high !== undefined && !(low === 0 && high === 0) && low <= high) {
    min = Math.max(min, low); max = Math.min(max, high); from = 'the servo\'s angle limits';
  }
  const range = document.getElementById('jog-position-range');
  const box = document.getElementById('jog-position');
  range.min = min; range.max = max; box.min = min; box.max = max;
  const present = servo.values.present_position;
  if (!jogRangeSet && present !== undefined) {
    const start = Math.min(max, Math.max(min, present));
    box.value = start; range.value = start;
  }
  jogRangeSet = true;
  document.getElementById('jog-range').textContent = `${withUnit(min, goal.scale)} .. ${withUnit(max, goal.scale)} (${from})`;
}
let jogRangeSet = false;

async function load() {
  servo = await api('GET', `/api/servo/${unit}`);
  document.title = `sms-gateway — unit ${unit}`;
  document.getElementById('title').textContent =
    `Unit ${servo.unit} — servo ${servo.id} on bus ${servo.bus} (${servo.map})${servo.name ? ' — ' + servo.name : ''}`;
  if (servo.values_error) say('reading the table: ' + servo.values_error, 'error');
  valueCells.clear();
  fieldsByName.clear();
  document.querySelector('#fields-table tbody').replaceChildren(...servo.fields.map((field) => {
    fieldsByName.set(field.name, field);
    const value = element('td', { class: 'num value' }, '');
    const raw = element('td', { class: 'num raw muted' }, '');
    valueCells.set(field.name, [value, raw]);
    showValue(field.name, servo.values[field.name]);
    return element('tr', { id: 'field-' + field.name, class: field.polled ? 'polled' : '' },
      element('td', {}, field.name), element('td', { class: 'num' }, field.address), element('td', {}, field.unit),
      element('td', {}, rangeText(field)), element('td', {}, field.area), element('td', {}, field.access), value, raw, editCell(field));
  }));
  setupJogRange();
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
    scales: { x: { type: 'linear', title: { display: true, text: 's' } }, y: { title: { display: true, text: '' } } },
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
    box.append(element('label', {}, box_, ' ' + label(field.name)));
    plotFields.push(field.name);
  }
}

// "present_voltage [V]": the plot's legend and the CSV's header; values in that unit.
function label(name) {
  const field = fieldsByName.get(name);
  const symbol = field && (field.scale ? field.scale.symbol : field.unit);
  return symbol ? `${name} [${symbol}]` : name;
}
function inUnit(name, raw) { const field = fieldsByName.get(name); return scaled(raw, field && field.scale); }

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
  const names = selected();
  chart.data.datasets = names.map((name, i) => ({
    label: label(name), borderColor: COLOURS[i % COLOURS.length], borderWidth: 1.5,
    data: rows.filter(([, v]) => name in v).map(([t, v]) => ({ x: t, y: inUnit(name, v[name]) })) }));
  // The axis names the units of what it shows (several fields: each unit once).
  const units = [...new Set(names.map((name) => { const f = fieldsByName.get(name); return f && (f.scale ? f.scale.symbol : f.unit); }).filter(Boolean))];
  chart.options.scales.y.title.text = units.join(', ');
  document.getElementById('plot').dataset.axis = units.join(', ');
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
  const lines = ['time_s,' + names.map(label).join(',')];
  for (const [t, v] of shown) lines.push([t.toFixed(4), ...names.map((n) => (n in v ? inUnit(n, v[n]) : ''))].join(','));
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
  if (last) for (const [name, value] of Object.entries(last[1])) showValue(name, value);
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
// A held move ended by a stop is said by the gateway (jog_ended), not by watchMove.
holdButton('hold-position', () => ({ type: 'jog', mode: 'position', value: Number(position.value) }));
holdButton('hold-speed', () => ({ type: 'jog', mode: 'speed', value: Number(document.getElementById('jog-speed').value) }));
window.addEventListener('blur', stopHold);
for (const [id, on] of [['torque-on', true], ['torque-off', false]]) {
  const button = document.getElementById(id);
  button.disabled = !canOperate;
  button.addEventListener('click', () => { if (on) watchMove('torque on', null); stream.send({ type: 'torque', on }); });
}
if (!canOperate) document.getElementById('jog-note').textContent = 'The jog panel needs the operate role.';

// --- a stop that cut this page's move short ------------------------------------------------------------
// After a write of this page or its torque on, a trip of the servo's bus's watchdog or an e-stop stops it
// (the safe stop): the page says so, with the time, rather than leave "written" standing.
let move = null;   // {what, goal, trips, estops}
let busFacts = null;
function watchMove(what, goal) {
  if (!busFacts) return;
  move = { what, goal, trips: busFacts.trips, estops: busFacts.estops };
}
onOverview((data) => {
  const bus = data.buses.find((b) => b.name === servo.bus);
  if (!bus || !bus.safety) return;
  busFacts = { trips: bus.safety.trips, estops: data.gateway.estop.count };
  if (!move) return;
  let by = null;
  if (bus.safety.trips > move.trips) {
    const at = new Date(Date.now() - (bus.safety.since_trip_ms || 0)).toLocaleTimeString('en-GB', { hour12: false });
    by = `the watchdog of bus ${bus.name} at ${at} (no write for ${bus.safety.timeout_ms} ms; re-arm it in the safety panel)`;
  } else if (data.gateway.estop.count > move.estops) {
    by = 'the e-stop';
  }
  if (!by) return;
  // A goal already reached was not cut short: the stop came after the move.
  const present = history.length ? history[history.length - 1][1].present_position : undefined;
  const reached = move.goal !== null && present !== undefined && Math.abs(present - move.goal) <= 5;
  const text = reached ? `${move.what}: reached its goal; then stopped by ${by}`
    : `${move.what}: stopped by ${by}` + (move.goal !== null && present !== undefined ? `, at position ${present}, short of its goal ${move.goal}` : '');
  document.getElementById('move-stopped').textContent = text;  // stays until the next stop: #message changes
  move = null;
});
