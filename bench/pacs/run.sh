#!/usr/bin/env bash
# Issue 51's PACS benchmark: retrieve + import of a 500-slice 512×512 int16 CT series from
# Orthanc (Debian's, with its DICOMweb plugin) on loopback.
#
# It starts Orthanc on a free loopback port with a temporary configuration and storage folder
# (the choices of app/tests/common/orthanc.rs: DICOMweb on, no DICOM port, no authentication),
# writes the CT phantom (`strata sample`, its first 500 slices) as 500 DICOM files (pydicom,
# Explicit VR Little Endian, 512 KiB of pixels each), stores them by STOW-RS (`strata pacs
# push`), then measures, RUNS times each (default 3), interleaved, medians reported:
#   a. `strata import URL --study S --series T STORE`: wall time and MB/s of DICOM bytes;
#   b. the retrieve alone: the time `strata import` reports for its retrieve phase ("retrieved
#      N instance(s), X MB, ... in R request(s), T s"; QIDO lists + WADO-RS per instance, 4 in
#      flight) against `curl` fetching the whole series as one WADO-RS multipart
#      (/studies/S/series/T, Accept: multipart/related; type="application/dicom";
#      transfer-syntax=*) to /dev/null: the throughput ratio (issue 51's goal: >= 0.8);
#   c. open to first image, the command-line proxy (not the viewer's own path): the import's
#      wall time plus `strata flythrough STORE --frames 1`'s "time to first frame" (open the
#      store, stream it, draw one 512² frame; on lavapipe where there is no GPU), and the same
#      with that process's whole wall time (start-up and GPU context included).
# `uptime` is printed before each run: the load the figures were taken under.
#
#   cargo build --release -p strata-app --bin strata
#   S=target/release/strata bash bench/pacs/run.sh
#   (W=work folder, RUNS=3, PARALLEL=4; SIZE=64 SLICES=40 RUNS=1 rehearses it in seconds)
#
# Needs: apt-get install -y orthanc orthanc-dicomweb curl; pip install pydicom numpy.
# Disk: about 1.1 GB under $W (the NRRD, the DICOM files, Orthanc's storage, one store and one
# retrieve folder at a time); everything under $W is deleted at the end (KEEP=1 keeps it).
set -u
S=$(realpath "${S:-target/release/strata}")
W=${W:-/tmp/strata-pacs-bench}
RUNS=${RUNS:-3}
PARALLEL=${PARALLEL:-4}
SLICES=${SLICES:-500}
SIZE=${SIZE:-512}
STUDY=1.2.826.0.1.3680043.8.498.51500
SERIES=$STUDY.1
rm -rf "$W"
mkdir -p "$W"
W=$(realpath "$W")
orthanc_pid=
cleanup() {
  if [ -n "$orthanc_pid" ]; then kill "$orthanc_pid" 2>/dev/null; wait "$orthanc_pid" 2>/dev/null; fi
  [ "${KEEP:-0}" = 1 ] || rm -rf "$W"
}
trap cleanup EXIT
now() { date +%s.%N; }
median() { sort -g | awk '{v[NR]=$1} END {print v[int((NR+1)/2)]}'; }
free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }

echo "== machine: $(nproc) cores, $(uptime)"
echo "== strata: $S ($("$S" --version))"

# --- the series -----------------------------------------------------------------------------
"$S" sample --size $SIZE --out "$W/phantom.nrrd" >/dev/null || exit 1
python3 - "$W/phantom.nrrd" "$W/dicom" $SLICES $STUDY $SERIES <<'EOF' || exit 1
import os, sys, numpy as np, pydicom
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import ExplicitVRLittleEndian
nrrd, out, slices, study, series = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4], sys.argv[5]
raw = open(nrrd, 'rb').read()
head = raw.index(b'\n\n') + 2
sizes = [l for l in raw[:head].decode().splitlines() if l.startswith('sizes:')][0].split()[1:]
nx, ny, nz = map(int, sizes)
vol = np.frombuffer(raw, dtype='<i2', offset=head).reshape(nz, ny, nx)
os.makedirs(out)
for k in range(slices):
    ds = Dataset()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.file_meta.MediaStorageSOPClassUID = '1.2.840.10008.5.1.4.1.1.2'
    ds.file_meta.MediaStorageSOPInstanceUID = f'{series}.{k + 1}'
    ds.SOPClassUID = '1.2.840.10008.5.1.4.1.1.2'
    ds.SOPInstanceUID = f'{series}.{k + 1}'
    ds.StudyInstanceUID = study; ds.SeriesInstanceUID = series
    ds.PatientName = 'BENCH^PHANTOM'; ds.PatientID = 'B-51'; ds.StudyDate = '20261206'
    ds.Modality = 'CT'; ds.StudyID = '1'; ds.SeriesNumber = 1; ds.InstanceNumber = k + 1
    ds.ImagePositionPatient = [-128.0, -128.0, 0.5 * k]
    ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
    ds.PixelSpacing = [0.5, 0.5]; ds.SliceThickness = 0.5
    ds.Rows = ny; ds.Columns = nx
    ds.SamplesPerPixel = 1; ds.PhotometricInterpretation = 'MONOCHROME2'
    ds.BitsAllocated = 16; ds.BitsStored = 16; ds.HighBit = 15; ds.PixelRepresentation = 1
    ds.RescaleSlope = 1; ds.RescaleIntercept = 0
    ds.PixelData = np.ascontiguousarray(vol[k]).tobytes()
    ds.save_as(f'{out}/{k:04}.dcm', enforce_file_format=True)
EOF
rm "$W/phantom.nrrd"
dicom_bytes=$(cat "$W"/dicom/*.dcm | wc -c)
echo "== series: $SLICES slices ${SIZE}x${SIZE} int16, $dicom_bytes bytes of DICOM files"

# --- Orthanc --------------------------------------------------------------------------------
plugin=$(ls /usr/share/orthanc/plugins/libOrthancDicomWeb.so* /usr/lib/orthanc/libOrthancDicomWeb.so* 2>/dev/null | head -1)
[ -n "$plugin" ] && [ -x /usr/sbin/Orthanc ] || { echo "no Orthanc: apt-get install -y orthanc orthanc-dicomweb"; exit 1; }
port=$(free_port)
dicom_port=$(free_port)
cat >"$W/orthanc.json" <<EOF
{ "Name": "strata-bench", "StorageDirectory": "$W/orthanc", "IndexDirectory": "$W/orthanc",
  "HttpPort": $port, "DicomServerEnabled": false, "DicomPort": $dicom_port,
  "RemoteAccessAllowed": false, "AuthenticationEnabled": false, "Plugins": ["$plugin"],
  "DicomWeb": { "Enable": true, "Root": "/dicom-web/", "EnableWado": true } }
EOF
/usr/sbin/Orthanc "$W/orthanc.json" >"$W/orthanc.log" 2>&1 &
orthanc_pid=$!
for _ in $(seq 600); do
  curl -s -o /dev/null "http://127.0.0.1:$port/dicom-web/studies" && break
  kill -0 $orthanc_pid 2>/dev/null || { cat "$W/orthanc.log"; exit 1; }
  sleep 0.1
done
URL=http://127.0.0.1:$port/dicom-web
export STRATA_PACS_SERVERS=/nonexistent/strata-bench-servers.json
t0=$(now)
"$S" pacs push "$URL" "$W/dicom" || exit 1
echo "== STOW-RS push: $(echo "$(now) - $t0" | bc) s"
rm -rf "$W/dicom"

# --- the runs -------------------------------------------------------------------------------
: >"$W/curl.txt"; : >"$W/import.txt"; : >"$W/retrieve.txt"; : >"$W/first.txt"
for run in $(seq "$RUNS"); do
  echo "== run $run: $(uptime)"
  # curl: the whole series as one multipart answer.
  read -r bytes secs < <(curl -s -o /dev/null -w '%{size_download} %{time_total}\n' \
    -H 'Accept: multipart/related; type="application/dicom"; transfer-syntax=*' \
    "$URL/studies/$STUDY/series/$SERIES")
  echo "curl: $bytes bytes in $secs s"
  echo "$bytes $secs" | awk '{print $1 / 1e6 / $2}' >>"$W/curl.txt"
  # strata import: retrieve (its own line) + import.
  rm -rf "$W/store"
  t0=$(now)
  "$S" import "$URL" --study $STUDY --series $SERIES --parallel "$PARALLEL" "$W/store" \
    >"$W/import.log" 2>&1 || { cat "$W/import.log"; exit 1; }
  wall=$(echo "$(now) - $t0" | bc)
  grep -a -E '^(retrieved|imported)' "$W/import.log"
  echo "import wall: $wall s"
  echo "$wall" >>"$W/import.txt"
  # "retrieved N instance(s), X MB, from URL in R request(s), T s (M MB/s)"
  sed -n -E 's/^retrieved .*, ([0-9.]+) MB, from .* request\(s\), ([0-9.]+) s .*/\1 \2/p' "$W/import.log" |
    awk '{print $1 / $2, $2}' >>"$W/retrieve.txt"
  # First image: a fresh process opens the store, streams it and draws one frame (its own
  # figure, "time to first frame", leaves out process and GPU start-up, which an open viewer
  # has behind it; the process's wall time is printed too).
  t0=$(now)
  "$S" flythrough "$W/store" --frames 1 --stops 1 --size 512x512 >"$W/first.log" 2>&1 ||
    { cat "$W/first.log"; exit 1; }
  process=$(echo "$(now) - $t0" | bc)
  first=$(sed -n -E 's/.*time to first frame \(open \+ first frame on the GPU\): ([0-9.]+) s.*/\1/p' "$W/first.log")
  echo "first frame: $first s (strata flythrough --frames 1; process wall $process s)"
  echo "$wall $first $process" | awk '{print $1 + $2, $1 + $3}' >>"$W/first.txt"
done

curl_mbs=$(median <"$W/curl.txt")
import_s=$(median <"$W/import.txt")
retrieve_mbs=$(cut -d' ' -f1 "$W/retrieve.txt" | median)
retrieve_s=$(cut -d' ' -f2 "$W/retrieve.txt" | median)
open_s=$(cut -d' ' -f1 "$W/first.txt" | median)
open_process_s=$(cut -d' ' -f2 "$W/first.txt" | median)
echo
echo "== medians of $RUNS runs ($SLICES x ${SIZE}^2 int16, $dicom_bytes bytes of DICOM, --parallel $PARALLEL)"
echo "a. strata import (retrieve + import): $import_s s, $(echo "$dicom_bytes $import_s" | awk '{printf "%.0f", $1 / 1e6 / $2}') MB/s of DICOM"
echo "b. retrieve alone: $retrieve_s s, $retrieve_mbs MB/s; curl WADO-RS series multipart: $curl_mbs MB/s; ratio $(echo "$retrieve_mbs $curl_mbs" | awk '{printf "%.2f", $1 / $2}') (goal >= 0.8)"
echo "c. open to first image: $open_s s (import wall + flythrough's time to first frame); with a fresh process's start-up and GPU: $open_process_s s"
echo "== $(uptime)"
