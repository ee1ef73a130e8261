-- Orthanc -> dsareg: when a biplane study becomes stable, ask dsareg to register it.
--
-- Install: list this file in Orthanc's "LuaScripts" (see examples/pacs/README.md), set the three
-- values below, and list PACS_DICOMWEB in dsareg's DSAREG_DICOMWEB_SERVERS (with the credentials
-- dsareg uses to read from / store to this Orthanc). dsareg fetches the images itself with
-- QIDO-RS / WADO-RS and stores the Spatial Registration object and the overlays back into the
-- same study with STOW-RS; this script only sends UIDs.
--
-- A study qualifies when it holds exactly two XA series (the AP and LAT planes; the one with the
-- smaller |Positioner Primary Angle| is taken as AP) and one 3D series (CT or MR, or an XA / RF
-- series with more than 10 instances: 3D-RA). A study that already holds a REG series is skipped,
-- so the results dsareg stores back (which make the study stable again) do not trigger a new job.

local DSAREG = "http://127.0.0.1:8000"                     -- the dsareg service
local PACS_DICOMWEB = "http://127.0.0.1:8042/dicom-web"    -- this Orthanc, as dsareg reaches it
local API_KEY = ""                                         -- dsareg API key ("" when auth is off)
local OPTIONS = {}                                         -- RegistrationOptions, e.g. { starts = 2 }

local function firstInstanceTags(series)
  return ParseJson(RestApiGet('/instances/' .. series['Instances'][1] .. '/simplified-tags'))
end

function OnStableStudy(studyId, tags, metadata)
  local studyUid = tags['StudyInstanceUID']
  local xa, volume = {}, nil
  for _, series in ipairs(ParseJson(RestApiGet('/studies/' .. studyId .. '/series'))) do
    local main = series['MainDicomTags']
    local modality = main['Modality']
    local count = #series['Instances']
    if modality == 'REG' then
      print('dsareg: study ' .. studyUid .. ' already registered, skipped')
      return
    elseif (modality == 'CT' or modality == 'MR') and volume == nil then
      volume = main['SeriesInstanceUID']
    elseif (modality == 'XA' or modality == 'RF') and count > 10 and volume == nil then
      volume = main['SeriesInstanceUID']
    elseif modality == 'XA' then
      local angle = tonumber(firstInstanceTags(series)['PositionerPrimaryAngle'] or '')
      if angle ~= nil then
        table.insert(xa, { uid = main['SeriesInstanceUID'], angle = math.abs(angle) })
      end
    end
  end
  if #xa ~= 2 or volume == nil then
    print('dsareg: study ' .. studyUid .. ' is not a biplane study with a 3D series, skipped')
    return
  end
  table.sort(xa, function(a, b) return a.angle < b.angle end)

  local request = {
    source = { dicomweb = {
      url = PACS_DICOMWEB, study_uid = studyUid,
      ap = { series_uid = xa[1].uid }, lat = { series_uid = xa[2].uid },
      volume = { series_uid = volume } } },
    store_results = true,
  }
  if next(OPTIONS) ~= nil then
    request['options'] = OPTIONS  -- an empty Lua table would be written as a JSON array
  end
  local headers = { ['Content-Type'] = 'application/json', ['Idempotency-Key'] = 'orthanc-' .. studyUid }
  if API_KEY ~= '' then
    headers['Authorization'] = 'Bearer ' .. API_KEY
  end
  local ok, answer = pcall(HttpPost, DSAREG .. '/v1/registrations', DumpJson(request, true), headers)
  if ok and answer ~= nil then
    print('dsareg: registration requested for study ' .. studyUid .. ': ' .. answer)
  else
    print('dsareg: could not reach ' .. DSAREG .. ' for study ' .. studyUid)
  end
end
